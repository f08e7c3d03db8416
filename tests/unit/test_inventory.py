"""The inventory model: examples load, every malformed input is one line, exit 2, nothing written."""

from __future__ import annotations

import pytest

from ccrp_cli.errors import InputError
from ccrp_cli.loader import load_inventory
from tests.conftest import INVENTORIES, LAB, run_ccrp

LAB_TEXT = LAB.read_text()


@pytest.mark.parametrize("path", INVENTORIES, ids=lambda p: p.name)
def test_example_inventories_validate(path, ccrp):
    proc = ccrp("fleet", "validate", "-i", str(path), "--json", check=True)
    assert '"fleet"' in proc.stdout


def test_lab_is_the_thesis_lab():
    inv = load_inventory(LAB)
    assert [(r.name, r.type) for r in inv.robots] == [("nao1", "nao"), ("nao2", "nao"), ("turtlebot1", "turtlebot")]
    assert inv.provider.kind == "docker" and inv.ros.distro == "noetic"
    assert inv.robot("nao2").imports == {"nao1": ["/faces"]}


BAD = {
    "bad-yaml": ("fleet: lab\nrobots: [nao1\n", "invalid YAML"),
    "not-a-mapping": ("- just\n- a list\n", "YAML mapping"),
    "unknown-key": (LAB_TEXT.replace("  distro: noetic", "  distro: noetic\n  colour: blue"), "ros.colour: unknown key"),
    "bad-robot-name": (LAB_TEXT.replace("name: nao1", "name: Nao-1"), "robots[0].name: 'Nao-1' does not match"),
    "duplicate-robot": (LAB_TEXT.replace("name: nao2", "name: nao1"), "duplicate robot name 'nao1'"),
    "duplicate-key": (LAB_TEXT.replace("fleet: lab", "fleet: lab\nfleet: lab2"), "duplicate key 'fleet'"),
    "overlapping-pools": (LAB_TEXT.replace("cidr: 10.90.0.0/24", "cidr: 10.80.5.0/24"), "overlaps"),
    "public-overlap": (LAB_TEXT.replace("public_cidr: 172.30.0.0/24", "public_cidr: 10.90.0.0/25"), "overlaps"),
    "unknown-distro": (LAB_TEXT.replace("distro: noetic", "distro: kinetic"), "ros.distro"),
    "unknown-provider": (LAB_TEXT.replace("kind: docker", "kind: azure"), "unknown provider kind 'azure'"),
    "import-not-exported": (LAB_TEXT.replace("nao2: [/faces]", "nao2: [/secrets]"), "does not export it"),
    "import-unknown-robot": (LAB_TEXT.replace("nao2: [/faces]", "nao7: [/faces]"), "unknown robot 'nao7'"),
    "export-loop": (LAB_TEXT.replace("exports: [/map]", "exports: [/map, /nao1/faces]"), "namespace"),
    "pool-exhausted": (
        LAB_TEXT.replace("pool: 10.80.0.0/16", "pool: 10.80.0.0/23").replace("subnet_prefix", "x"),
        "room for 1",
    ),
    "bad-port": (LAB_TEXT.replace("port: 1194", "port: 70000"), "vpn.port"),
    "fkie-engine": (LAB_TEXT.replace("engine: relay", "engine: fkie"), "sharing.engine: fkie needs multimaster_fkie"),
    "unknown-engine": (LAB_TEXT.replace("engine: relay", "engine: zenoh"), "sharing.engine"),
    "gateway-on-docker": (LAB_TEXT.replace("kind: docker", "kind: docker\n  entry: gateway"),
                          "provider.entry: gateway: the docker backend makes no entry gateway"),
    "unknown-entry": (LAB_TEXT.replace("kind: docker", "kind: docker\n  entry: bastion"), "provider.entry"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_inventory_is_one_line_exit_2_nothing_written(case, tmp_path):
    text, expected = BAD[case]
    inv = tmp_path / "inv.yaml"
    inv.write_text(text)
    home = tmp_path / "home"
    for args in (["fleet", "validate"], ["vpn", "init"], ["vpn", "issue-cert", "--robot", "nao1"]):
        proc = run_ccrp(*args, "-i", str(inv), home=home)
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.splitlines()
        assert len(lines) == 1, proc.stderr
        assert expected in lines[0]
        assert "Traceback" not in proc.stderr and proc.stdout == ""
    assert not home.exists(), "a rejected inventory must not create any file"


def test_missing_inventory_file(tmp_path):
    proc = run_ccrp("fleet", "validate", "-i", str(tmp_path / "nope.yaml"), home=tmp_path / "h")
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1 and "not found" in proc.stderr


def test_load_inventory_raises_input_error(tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text("fleet: 9lab\nprovider: {kind: docker}\n")
    with pytest.raises(InputError, match=r"fleet: '9lab' does not match"):
        load_inventory(p)


def test_fkie_is_refused_by_every_command_in_one_line(tmp_path):
    """multimaster_fkie is not in Debian, which every clone runs: no command accepts the engine, and
    the one line says where fkie exists and what to use instead."""
    # A path relative to the command's directory: a long one is cut in the line (a parallel run's
    # temporary directories are longer), and what is checked here is the rest of it.
    inv = "fleet.yaml"
    (tmp_path / inv).write_text(LAB_TEXT.replace("engine: relay", "engine: fkie"))
    home = tmp_path / "home"
    for args in (["fleet", "validate"], ["fleet", "up"], ["status"], ["topics"], ["snapshot", "build"]):
        proc = run_ccrp(*args, "-i", inv, home=home, cwd=tmp_path)
        assert proc.returncode == 2, (args, proc.stderr)
        line, = proc.stderr.splitlines()
        assert line == (f"ccrp: error: {inv}: sharing.engine: fkie needs multimaster_fkie, available only for ROS 1 "
                        "on Ubuntu 20.04 from packages.ros.org; ccrp's clones run Debian 12, which does not package "
                        "it: use engine: relay"), line
    assert not home.exists()
