"""No input reaches a rendered file unchecked: every free-form field of the inventory and every
string option of the CLI, fed control characters, newlines, quotes and over-long values, either
exits 2 with one line on stderr or lands in the rendered file verbatim, as one token."""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ccrp_cli.models.values import Endpoint, check_cloud_name, parse_endpoint
from tests.conftest import INVENTORIES, LAB, ROOT
from tests.inprocess_cli import run_ccrp_inprocess
from tests.unit.trees import nodes, replaced

# A token in a rendered file: no whitespace, no control character, no quote or backslash.
TOKEN = re.compile(r"[^\s\x00-\x1f\x7f-\x9f'\"\\]+")
PROPERTY = settings(max_examples=100, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

HOSTILE_PARTS = ["\n", "\r", "\t", " ", "\x00", "\x07", "\x1b[2J", "\x85", "\u2028", "'", '"', "\\", "#", ";",
                 "\nscript-security 2\nup /bin/sh", "\nRUN id", "[", "]", ":", "%eth0", "/", "..", "é"]


def hostile(seed: st.SearchStrategy[str]) -> st.SearchStrategy[str]:
    """A plausible value with hostile parts around or inside it, or a long one."""
    part = st.sampled_from(HOSTILE_PARTS)
    mixed = st.tuples(seed, part, seed).map("".join)
    long = st.tuples(seed, st.integers(100, 5000)).map(lambda t: (t[0] or "a") * t[1])
    return st.one_of(seed, mixed, st.tuples(part, seed).map("".join), st.tuples(seed, part).map("".join), long,
                     st.text(max_size=40))


HOSTS = st.one_of(
    st.from_regex(r"[a-z][a-z0-9-]{0,10}(\.[a-z][a-z0-9]{0,8}){0,3}", fullmatch=True),
    st.ip_addresses(v=4).map(str),
    st.ip_addresses(v=6).map(str),
)
PORTS = st.integers(0, 70000).map(str)
ENDPOINTS = st.one_of(
    HOSTS,
    st.tuples(HOSTS, PORTS).map(lambda t: f"[{t[0]}]:{t[1]}" if ":" in t[0] else f"{t[0]}:{t[1]}"),
    st.ip_addresses(v=6).map(lambda a: f"[{a}]"),
)


def one_line_exit_2(code: int, out: str, err: str) -> None:
    lines = err.splitlines()
    assert code == 2, (code, err[:500])
    assert len(lines) == 1 and len(lines[0]) <= 300 and lines[0].startswith("ccrp: error: "), err[:1000]
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def lab_home(tmp_path_factory) -> Path:
    """CCRP_HOME with the lab's CA and nao1's certificates."""
    home = tmp_path_factory.mktemp("home")
    for args in (["vpn", "init"], ["vpn", "issue-cert", "--robot", "nao1"]):
        code, _, err = run_ccrp_inprocess(*args, "-i", str(LAB), home=home)
        assert code == 0, err
    return home


def edge(home: Path, out: Path, *extra: str) -> tuple[int, str, str]:
    return run_ccrp_inprocess("render", "edge", "-i", str(LAB), "--out", str(out), *extra, home=home)


def profile_without_remote(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if not line.startswith("remote ")]


# -- endpoints ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, host, port", [
    ("198.51.100.7", "198.51.100.7", 1194),
    ("clone.example.org:443", "clone.example.org", 443),
    ("2001:db8::1", "2001:db8::1", 1194),
    ("[2001:db8::1]", "2001:db8::1", 1194),
    ("[2001:db8::1]:1194", "2001:db8::1", 1194),
    ("[2001:db8::1]:443", "2001:db8::1", 443),
])
def test_endpoint_forms(text, host, port):
    assert parse_endpoint(text, 1194) == Endpoint(host, port)


@pytest.mark.parametrize("text", [
    "1.2.3.4\nscript-security 2", "host name", "[2001:db8::1", "[2001:db8::1]x", "2001:db8::1]:1194",
    "fe80::1%eth0", "host:0", "host:65536", "host:١٢", "-host", "a" * 254, "", ":1194", "h'ost",
])
def test_endpoint_refusals(text):
    with pytest.raises(ValueError):
        parse_endpoint(text, 1194)


def test_ipv6_endpoint_renders_bare_in_the_profile(lab_home, tmp_path):
    for remote in ("[2001:db8::1]:1194", "2001:db8::1"):
        code, _, err = edge(lab_home, tmp_path / "e", "--robot", "nao1", "--remote", remote)
        assert code == 0, err
        assert "remote 2001:db8::1 1194" in (tmp_path / "e" / "robot.ovpn").read_text().splitlines()


@PROPERTY
@given(remote=st.one_of(ENDPOINTS, hostile(ENDPOINTS)))
def test_remote_option_is_refused_or_one_token(lab_home, tmp_path, remote):
    out = tmp_path / "edge"
    code, _, err = edge(lab_home, out, "--robot", "nao1", "--remote", remote)
    if code != 0:
        return one_line_exit_2(code, "", err)
    endpoint = parse_endpoint(remote, 1194)
    lines = (out / "robot.ovpn").read_text().splitlines()
    assert [line for line in lines if line.startswith("remote ")] == [f"remote {endpoint.host} {endpoint.port}"]
    assert TOKEN.fullmatch(endpoint.host) and endpoint.host in remote
    reference = tmp_path / "reference"
    if not reference.exists():
        assert edge(lab_home, reference, "--robot", "nao1", "--remote", "192.0.2.1")[0] == 0
    assert profile_without_remote(out / "robot.ovpn") == profile_without_remote(reference / "robot.ovpn")


def test_public_endpoint_in_state_is_checked(lab_home, tmp_path):
    """state.json is a file on disk too: its public_endpoint is parsed when read, and an IPv6
    address recorded there renders bare."""
    import shutil

    home = tmp_path / "home"
    shutil.copytree(lab_home, home)
    state = home / "lab" / "state.json"
    cases = (("2001:db8::1", True), ("198.51.100.9\nscript-security 2", False), ("x" * 10_000, False))
    for n, (endpoint, ok) in enumerate(cases):
        state.write_text(json.dumps({"fleet": "lab", "robots": {"nao1": {"index": 1, "public_endpoint": endpoint}}}))
        out = tmp_path / f"e{n}"
        code, _, err = edge(home, out, "--robot", "nao1")
        if ok:
            assert code == 0 and "remote 2001:db8::1 1194" in (out / "robot.ovpn").read_text(), err
            continue
        line, = err.splitlines()
        assert code == 1 and "does not match the state schema" in line and len(line) <= 300, line
        assert not out.exists()


# -- the other string options --------------------------------------------------------------------------

@PROPERTY
@given(robot=hostile(st.sampled_from(["nao1", "nao2", "robot"])))
def test_robot_option_is_refused_or_a_member(lab_home, tmp_path, robot):
    out = Path(tempfile.mkdtemp(dir=tmp_path)) / "edge"  # tmp_path is shared by the examples
    code, _, err = edge(lab_home, out, "--robot", robot, "--remote", "192.0.2.1")
    if robot == "nao1":
        assert code == 0, err
    elif robot == "nao2":  # a member without certificates: exit 1, the hint names issue-cert
        assert code == 1 and "issue-cert" in err
    else:
        one_line_exit_2(code, "", err)
        assert not out.exists()


@PROPERTY
@given(name=hostile(st.from_regex(r"[a-z][a-z0-9._-]{0,12}", fullmatch=True)))
def test_out_option_is_written_there_or_one_line(lab_home, tmp_path, name):
    """--out is taken as a path: the bundle lands exactly there, or 'cannot write' in one line."""
    out = tmp_path / ("o" + name.replace("/", "_"))
    code, _, err = edge(lab_home, out, "--robot", "nao1", "--remote", "192.0.2.1")
    if code == 0:
        assert (out / "robot.ovpn").is_file() and json.loads((out / "manifest.json").read_text())["robot"] == "nao1"
    else:
        one_line_exit_2(code, "", err)
        assert "cannot write" in err or "'--out'" in err  # a NUL byte is refused by the parser


@pytest.mark.parametrize("where", ["file", "proc", "long"])
def test_out_into_an_unwritable_place_is_one_line(lab_home, tmp_path, where):
    (tmp_path / "file").write_text("")
    out = {"file": tmp_path / "file" / "edge", "proc": Path("/proc/ccrp-edge"), "long": tmp_path / ("x" * 300)}[where]
    code, _, err = edge(lab_home, out, "--robot", "nao1", "--remote", "192.0.2.1")
    one_line_exit_2(code, "", err)
    assert "cannot write" in err


@PROPERTY
@given(path=hostile(st.just("inventories/lab.yaml")))
def test_inventory_option_is_refused_in_one_line(tmp_path, path):
    code, _, err = run_ccrp_inprocess("fleet", "validate", "-i", path, home=tmp_path / "home")
    if Path(path) != Path("inventories/lab.yaml"):  # pathlib drops a trailing / or a doubled //
        one_line_exit_2(code, "", err)


# Options handed to a cloud or to Docker as a name (checked at parse time, before the fleet opens).
CLOUD_OPTIONS = {
    "snapshot-bake --base-image": lambda v: ("snapshot", "bake", "-i", str(ROOT / "inventories" / "aws.yaml"), "--base-image", v),
    "snapshot-delete SNAPSHOT": lambda v: ("snapshot", "delete", "-i", str(LAB), "--", v),
    "robot-sim --network": lambda v: ("robot", "sim", "-i", str(ROOT / "inventories" / "aws.yaml"), "-r", "nao1", "--network", v),
}
CLOUD_NAMES = st.sampled_from(["ami-0abc123", "projects/debian-cloud/global/images/family/debian-12",
                               "resolve:ssm:/aws/service/debian/release/12/latest/amd64", "debian-12", "bridge"])


@pytest.mark.parametrize("option", sorted(CLOUD_OPTIONS))
@PROPERTY
@given(value=hostile(CLOUD_NAMES))
def test_cloud_name_options_are_refused_or_one_token(tmp_path, option, value):
    try:
        check_cloud_name(value)
    except ValueError:
        one_line_exit_2(*run_ccrp_inprocess(*CLOUD_OPTIONS[option](value), home=tmp_path / "home"))
        assert not (tmp_path / "home").exists()
    else:  # accepted: it would go to the cloud as it is, a single token
        assert TOKEN.fullmatch(value) and len(value) <= 255


# -- the inventory's free-form fields -----------------------------------------------------------------

BASES = [yaml.safe_load(p.read_text()) for p in INVENTORIES]
# The examples carry no base_image, instance_type or zone: give them one each to be fuzzed too.
BASES[[b["provider"]["kind"] for b in BASES].index("docker")]["provider"]["base_image"] = "ccrp/base:bookworm"
for _base in BASES:
    _base["robots"][0].update(instance_type="m1.small", zone="zone-a")
LEAVES = [(i, path, value) for i, base in enumerate(BASES) for path, value in nodes(base) if isinstance(value, str)]


@settings(max_examples=200, deadline=None, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(leaf=st.sampled_from(LEAVES), data=st.data())
def test_inventory_strings_are_refused_or_one_token(tmp_path, leaf, data):
    index, path, original = leaf
    value = data.draw(hostile(st.just(original)))
    tmp = Path(tempfile.mkdtemp(dir=tmp_path))  # tmp_path is shared by the examples
    inventory = tmp / "inventory.yaml"
    inventory.write_text(yaml.safe_dump(replaced(BASES[index], path, value), sort_keys=False))
    code, out, err = run_ccrp_inprocess("fleet", "validate", "-i", str(inventory), home=tmp / "home")
    if code != 0:
        one_line_exit_2(code, out, err)
        return
    assert TOKEN.fullmatch(value), f"{'.'.join(map(str, path))} accepted {value!r}"
    if path[-1] == "base_image":  # written into a file ccrp generates (as software's are: test_workloads.py)
        from ccrp_cli.providers.docker.images import dockerfile
        from ccrp_cli.recipes import platform
        from ccrp_cli.services.registry import image_agents

        text = dockerfile("lab", "noetic", value, platform("noetic", "debian-bookworm"), agents=image_agents())
        # The value is one token of the first FROM; the others name the Dockerfile's own stages.
        assert [line for line in text.splitlines() if line.startswith("FROM")] == [
            f"FROM {value} AS clone", "FROM clone AS agents", "FROM clone AS image"]
