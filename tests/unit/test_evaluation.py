"""`ccrp bench` and `robot sim --link`: what is parsed before anything runs, and the statistics."""

from __future__ import annotations

import pytest

from ccrp_cli.errors import InputError
from ccrp_cli.evaluation import parse_counts, parse_list, summary
from ccrp_cli.simulated import PRESETS, Link, parse_link
from tests.conftest import LAB
from tests.unit.inprocess_cli import run_ccrp_inprocess


@pytest.mark.parametrize("text, link", [
    ("eu", PRESETS["eu"]),
    ("us", PRESETS["us"]),
    ("80", Link(80)),
    ("80/5", Link(80, 5)),
    ("120/10/0.5", Link(120, 10, 0.5)),
    ("0", Link(0)),
])
def test_link_forms(text, link):
    assert parse_link(text) == link
    assert parse_link(link.spec) == link  # the spec a running robot's unit keeps gives the same link back


@pytest.mark.parametrize("text", ["none", "off"])
def test_no_link(text):
    assert parse_link(text) is None


@pytest.mark.parametrize("text", ["", "fast", "-5", "80ms", "80/5/1/2", "10/20", "10/5/100", "20000", "1e3", "80/ 5",
                                  "eu\n", "80;reboot"])
def test_link_refusals(text):
    with pytest.raises(InputError):
        parse_link(text)


def test_presets_are_the_thesis_round_trips():
    assert (PRESETS["eu"].rtt_ms, PRESETS["us"].rtt_ms) == (50, 180)
    assert str(PRESETS["eu"]).startswith("eu (rtt 50 ms")


@pytest.mark.parametrize("text, counts", [("1..10", list(range(1, 11))), ("3", [3]), ("5,1,2,2", [1, 2, 5])])
def test_robot_counts(text, counts):
    assert parse_counts(text) == counts


@pytest.mark.parametrize("text", ["0..3", "1..", "a", "", "1..101", "3..1", "-1"])
def test_robot_count_refusals(text):
    with pytest.raises(InputError):
        parse_counts(text)


def test_task_and_model_lists():
    assert parse_list("100, 500", None, "--task-ms") == [100.0, 500.0]
    assert parse_list("pbm,cbm", ("cbm", "pbm"), "--model") == ["pbm", "cbm"]
    for text in ("", "x", "-1", "70000"):
        with pytest.raises(InputError):
            parse_list(text, None, "--task-ms")
    for text in ("", "cbm,xbm"):
        with pytest.raises(InputError):
            parse_list(text, ("cbm", "pbm"), "--model")


def test_summary():
    s = summary([float(x) for x in range(1, 101)])
    assert s == {"mean_ms": 50.5, "p50_ms": 50.5, "p95_ms": 95.0, "max_ms": 100.0, "samples": 100}
    assert summary([7.0])["p95_ms"] == 7.0
    assert summary([]) == {"mean_ms": None, "p50_ms": None, "p95_ms": None, "max_ms": None, "samples": 0}


@pytest.mark.parametrize("argv", [
    ("robot", "sim", "-r", "nao1", "--link", "10/20"),
    ("robot", "sim", "-r", "nao1", "--link", "lan"),
    ("bench", "qos", "--robots", "0..3"),
    ("bench", "qos", "--model", "cbm,proxy"),
    ("bench", "qos", "--task-ms", "fast"),
    ("bench", "qos", "--link", "mars"),
    ("bench", "rtt", "-r", "nao1", "--samples", "0"),
    ("bench", "teleop", "-r", "nao1", "--duration", "0"),
])
def test_bad_bench_input_is_one_line_and_touches_nothing(tmp_path, argv):
    """Refused before the fleet is opened: no state, no Docker call (none runs in unit tests)."""
    code, out, err = run_ccrp_inprocess(*argv, "-i", str(LAB), home=tmp_path / "home")
    assert code == 2, (out, err)
    assert err.startswith("ccrp: error: ") and err.count("\n") == 1, err
    assert not (tmp_path / "home").exists()


def test_unknown_robot_is_refused_before_docker(tmp_path):
    code, _, err = run_ccrp_inprocess("bench", "rtt", "-i", str(LAB), "-r", "ghost", home=tmp_path / "home")
    assert code == 2 and "ghost" in err and err.count("\n") == 1, err
