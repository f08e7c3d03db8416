"""`ccrp bench` and `robot sim --link`: what is parsed before anything runs, and the statistics."""

from __future__ import annotations

import pytest

from ccrp_cli.errors import InputError
from ccrp_cli.robot.evaluation import parse_counts, parse_list, summary
from ccrp_cli.robot.simulated import PRESETS, Link, parse_link
from tests.conftest import LAB
from tests.inprocess_cli import run_ccrp_inprocess


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


def _ipv4(body: bytes, flags: int = 0) -> bytes:
    import struct

    header = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(body), 0x1234, flags, 64, 17, 0,
                         bytes([10, 0, 0, 2]), bytes([203, 0, 113, 7]))
    return header + body


def test_the_link_fragments_what_is_larger_than_the_path_mtu():
    """ccrp-link sends outgoing packets again from a raw socket with the header included, which
    does not fragment: an OpenVPN datagram carrying a full 1500-byte tunnel packet (ROS 2's image
    fragments) was lost on every emulated link. It now splits them as the kernel would."""
    import runpy
    import struct

    from tests.conftest import ROOT

    link = runpy.run_path(str(ROOT / "templates" / "sim" / "ccrp-link"), run_name="ccrp_link")
    body = bytes(range(256)) * 6 + b"tail"  # 1540 bytes: 1560 with the header, over 1500
    pieces = link["fragments"](_ipv4(body), 1500)
    assert len(pieces) == 2 and all(len(p) <= 1500 for p in pieces)
    got = b""
    for i, piece in enumerate(pieces):
        length, ident, flags = struct.unpack_from("!HHH", piece, 2)
        assert length == len(piece) and ident == 0x1234
        assert bool(flags & 0x2000) == (i == 0) and (flags & 0x1FFF) * 8 == len(got)
        assert link["checksum"](piece[:20]) == 0  # a valid header checksum sums to zero
        got += piece[20:]
    assert got == body
    small = _ipv4(b"x" * 100)
    assert link["fragments"](small, 1500) == [small]
    dont = _ipv4(body, flags=0x4000)  # DF: kept whole (and lost, as on a real path)
    assert link["fragments"](dont, 1500) == [dont]
