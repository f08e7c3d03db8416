"""The robot's own software (docs/workloads.md): the inventory's `software:`, its merge, the
workspace's packages and their dependencies, the snapshot's digest, the node units, logs."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import yaml

from ccrp_cli.errors import InputError
from ccrp_cli.loader import parse_inventory
from ccrp_cli.models.software import Software, merge
from ccrp_cli.providers.docker import images
from ccrp_cli.recipes import platform
from ccrp_cli.services.workloads import (
    INDEX,
    NO_SOFTWARE,
    absent_index,
    apply_nodes,
    log_units,
    node_files,
    node_unit,
    read_journal,
    snapshot_software,
    systemd_word,
)
from tests.conftest import LAB
from tests.inprocess_cli import run_ccrp_inprocess

CATKIN_XML = """<?xml version="1.0"?>
<package format="2">
  <name>{name}</name><version>1.0.0</version><description>x</description>
  <maintainer email="a@b.c">a</maintainer><license>MIT</license>
  <buildtool_depend>catkin</buildtool_depend>
  {deps}
</package>
"""
AMENT_XML = """<?xml version="1.0"?>
<package format="3">
  <name>{name}</name><version>1.0.0</version><description>x</description>
  <maintainer email="a@b.c">a</maintainer><license>MIT</license>
  {deps}
  <export><build_type>{build_type}</build_type></export>
</package>
"""


def lab(**top) -> dict:
    data = yaml.safe_load(LAB.read_text())
    data.update(top)
    return data


def inventory(data: dict, where=None):
    return parse_inventory(data, str(where or "inventory.yaml"))


def workspace(root, name: str, xml: str, **files):
    pkg = root / "src" / name
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text(xml)
    for rel, text in files.items():
        (pkg / rel).write_text(text)
    return root


# -- the inventory --------------------------------------------------------------------------------

def test_software_merges_fleet_then_type_then_robot():
    data = lab(software={"apt": ["htop"], "run": [{"name": "mapper", "command": ["mapper", "--fast"]}]},
               types={"nao": {"software": {"pip": ["numpy>=1.24"], "run": [{"name": "faces", "command": ["faces"]}]}}})
    data["robots"][0]["software"] = {"apt": ["htop", "tree"], "run": [{"name": "mapper", "command": ["mapper", "--slow"]}]}
    inv = inventory(data)
    nao1, nao2, turtle = inv.robots
    mine = inv.software_of(nao1)
    assert mine.apt == ["htop", "tree"] and mine.pip == ["numpy>=1.24"]
    assert [(n.name, n.command) for n in mine.run] == [("mapper", ["mapper", "--slow"]), ("faces", ["faces"])]
    assert [n.command for n in inv.software_of(nao2).run] == [["mapper", "--fast"], ["faces"]]
    assert [n.name for n in inv.software_of(turtle).run] == ["mapper"]  # a turtlebot: not the nao type's
    snap = inv.snapshot_software()  # the union, without nodes: one snapshot serves every clone
    assert snap.apt == ["htop", "tree"] and snap.pip == ["numpy>=1.24"] and snap.run == []
    assert merge(None, Software()).run == []


@pytest.mark.parametrize("software, words", [
    ({"run": [{"name": "Mapper", "command": ["x"]}]}, "name"),
    ({"run": [{"name": "a b", "command": ["x"]}]}, "name"),
    ({"run": [{"name": "m", "command": "python3 -m pkg.node"}]}, "list of words"),
    ({"run": [{"name": "m", "command": ["roslaunch", "x.launch", "&&", "rm", "-rf", "/"]}]}, "shell"),
    ({"run": [{"name": "m", "command": ["a", "|", "b"]}]}, "shell"),
    ({"run": [{"name": "m", "command": ["a\nExecStartPre=/bin/sh"]}]}, "control character"),
    ({"run": [{"name": "m", "command": []}]}, "at least 1"),
    ({"run": [{"name": "m", "command": ["a"]}, {"name": "m", "command": ["b"]}]}, "given twice"),
    ({"run": [{"name": "m", "command": ["a"], "memory": "lots"}]}, "memory"),
    ({"run": [{"name": "m", "command": ["a"], "memory": 512}]}, "no unit"),
    ({"run": [{"name": "m", "command": ["a"], "cpu": True}]}, "CPU cores"),
    ({"apt": ["Bad_Name"]}, "apt"),
    ({"apt": ["ros-core; rm -rf /"]}, "apt"),
    ({"pip": ["--index-url=http://evil"]}, "not a pip requirement"),
    ({"pip": ["pkg @ https://evil.example/pkg.whl"]}, "URL"),
    ({"pip": ['numpy; python_version<"3.12"']}, "markers"),
    ({"workspace": "/abs/ws"}, "relative"),
    ({"workspace": "../outside"}, "relative"),
    ({"what": 1}, "what"),
])
def test_bad_software_is_one_line_naming_the_field(software, words):
    with pytest.raises(InputError) as bad:
        inventory(lab(software=software))
    line = bad.value.one_line()
    assert "\n" not in line and words.lower() in line.lower(), line


def test_the_workspace_is_fleet_wide():
    with pytest.raises(InputError, match="fleet-wide"):
        inventory(lab(types={"nao": {"software": {"workspace": "ws"}}}))
    data = lab()
    data["robots"][1]["software"] = {"workspace": "ws"}
    with pytest.raises(InputError, match="fleet-wide"):
        inventory(data)


# -- the workspace --------------------------------------------------------------------------------

def test_a_catkin_workspace_resolves_to_debian_packages_and_changes_the_digest(tmp_path):
    deps = "".join(f"<depend>{k}</depend>" for k in ("roscpp", "sensor_msgs", "nav_msgs", "helper"))
    ws = workspace(tmp_path / "ws", "mapper", CATKIN_XML.format(name="mapper", deps=deps), **{"main.cpp": "int main(){}"})
    workspace(ws, "helper", CATKIN_XML.format(name="helper", deps=""))  # the workspace's own: not a key
    (ws / "build").mkdir()
    (ws / "build" / "junk.o").write_bytes(b"\0" * 10)  # build output: neither built nor digested
    inv = inventory(lab(software={"workspace": "ws", "apt": ["htop"]}))
    snap = snapshot_software(inv, tmp_path / "inventory.yaml")
    assert {p.name for p in snap.packages} == {"mapper", "helper"} and snap.build_type == "catkin"
    assert snap.apt == ["htop", "catkin", "libroscpp-dev", "libsensor-msgs-dev", "python3-sensor-msgs",
                        "libnav-msgs-dev", "python3-nav-msgs"]
    assert not any(rel.startswith("build/") for rel, _ in snap.workspace)
    before = snap.digest
    (ws / "build" / "junk.o").write_bytes(b"\1")
    assert snapshot_software(inv, tmp_path / "inventory.yaml").digest == before
    (ws / "src" / "mapper" / "main.cpp").write_text("int main(){return 0;}")
    assert snapshot_software(inv, tmp_path / "inventory.yaml").digest != before
    text = images.dockerfile("lab", "noetic", images.DEFAULT_BASE, platform("noetic", "debian-bookworm"), snap, agents=("relay", "api_manager"))
    assert "FROM image AS workspace" in text and "catkin_make install" in text and "-DCMAKE_INSTALL_PREFIX=/opt/ccrp/workspace" in text
    assert "COPY --from=workspace /opt/ccrp/workspace /opt/ccrp/workspace" in text
    assert f"LABEL ccrp-software={snap.digest}" in text
    assert snapshot_software(inventory(lab()), None).digest == NO_SOFTWARE


def test_pip_requirements_reach_the_snapshots_pip_as_one_word_each(tmp_path):
    """A Dockerfile RUN line is a shell's: `numpy<2` unquoted would read a file named 2."""
    snap = snapshot_software(inventory(lab(software={"pip": ["numpy<2", "scipy>=1.10,!=1.11.0", "rich"]})), None)
    text = images.dockerfile("lab", "noetic", images.DEFAULT_BASE, platform("noetic", "debian-bookworm"), snap, agents=("relay", "api_manager"))
    assert "/tmp/ccrp-software-wheels 'numpy<2' 'scipy!=1.11.0,>=1.10' rich \\\n" in text


def test_an_unknown_key_names_itself_and_its_package_before_anything(tmp_path):
    workspace(tmp_path / "ws", "mapper", CATKIN_XML.format(name="mapper", deps="<depend>octomap_server</depend>"))
    with pytest.raises(InputError) as bad:
        snapshot_software(inventory(lab(software={"workspace": "ws"})), tmp_path / "inventory.yaml")
    assert "mapper" in str(bad.value) and "octomap_server" in str(bad.value)


def test_ros2_takes_ament_python_and_refuses_rclcpp(tmp_path):
    jazzy = lab(software={"workspace": "ws"}, ros={"distro": "jazzy"})
    for robot in jazzy["robots"]:
        robot.pop("services", None)
    jazzy.pop("services", None)
    deps = "<exec_depend>rclpy</exec_depend><exec_depend>nav_msgs</exec_depend>"
    workspace(tmp_path / "ws", "offload", AMENT_XML.format(name="offload", deps=deps, build_type="ament_python"),
              **{"setup.py": "from setuptools import setup; setup(name='offload')"})
    snap = snapshot_software(inventory(jazzy), tmp_path / "inventory.yaml")
    assert snap.pip == ["ros-jazzy-nav-msgs==5.3.6"] and snap.apt == []
    text = images.dockerfile("lab", "jazzy", images.DEFAULT_BASE, platform("jazzy", "debian-bookworm"), snap, agents=("relay", "api_manager"))
    assert "/opt/ros/jazzy/bin/pip install --no-index --no-cache-dir --find-links /tmp/ccrp-software-wheels ros-jazzy-nav-msgs==5.3.6 wheel" in text
    assert "/tmp/ccrp-ws/src/offload" in text
    for deps, build_type in (("<depend>rclcpp</depend>", "ament_python"), ("", "ament_cmake")):
        (tmp_path / "ws" / "src" / "offload" / "package.xml").write_text(
            AMENT_XML.format(name="offload", deps=deps, build_type=build_type))
        with pytest.raises(InputError, match="rclcpp"):
            snapshot_software(inventory(jazzy), tmp_path / "inventory.yaml")


def test_a_package_path_that_would_split_the_build_command_is_refused(tmp_path):
    workspace(tmp_path / "ws", "a b\nRUN touch x", CATKIN_XML.format(name="mapper", deps=""))
    with pytest.raises(InputError, match="package path"):
        snapshot_software(inventory(lab(software={"workspace": "ws"})), tmp_path / "inventory.yaml")


def test_a_missing_or_empty_workspace_is_one_line(tmp_path):
    inv = inventory(lab(software={"workspace": "ws"}))
    with pytest.raises(InputError, match="no directory"):
        snapshot_software(inv, tmp_path / "inventory.yaml")
    (tmp_path / "ws").mkdir()
    with pytest.raises(InputError, match="no package.xml"):
        snapshot_software(inv, tmp_path / "inventory.yaml")
    (tmp_path / "ws" / "link").symlink_to("/etc")
    (tmp_path / "ws" / "package.xml").write_text("<package><name>x")
    with pytest.raises(InputError, match="outside the workspace"):
        snapshot_software(inv, tmp_path / "inventory.yaml")


@pytest.mark.parametrize("link", ["absolute", "relative"])
def test_a_workspace_that_links_out_of_the_inventorys_directory_is_refused(tmp_path, link):
    """Issue 39: `ws -> ~` pulled the operator's home into the snapshot's build."""
    home = workspace(tmp_path / "home", "mapper", CATKIN_XML.format(name="mapper", deps=""))
    (home / "id_ed25519").write_text("PRIVATE KEY")
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    (fleet / "ws").symlink_to(home if link == "absolute" else "../home")
    with pytest.raises(InputError) as err:
        snapshot_software(inventory(lab(software={"workspace": "ws"})), fleet / "inventory.yaml")
    line = err.value.one_line()
    assert "\n" not in line and "leads out of the inventory's directory" in line and str(home) in line


def test_a_workspace_linked_within_the_inventorys_directory_is_read(tmp_path):
    workspace(tmp_path / "src-tree" / "ws", "mapper", CATKIN_XML.format(name="mapper", deps=""))
    (tmp_path / "ws").symlink_to("src-tree/ws")
    out = snapshot_software(inventory(lab(software={"workspace": "ws"})), tmp_path / "inventory.yaml")
    assert [p.name for p in out.packages] == ["mapper"]


# -- the node units -------------------------------------------------------------------------------

def test_a_command_reaches_systemd_word_for_word():
    assert systemd_word('a "b" $HOME %n \\x') == '"a \\"b\\" $$HOME %%n \\\\x"'
    inv = inventory(lab(software={"run": [{"name": "mapper", "command": ["python3", "-m", "pkg.node", "--name=$X"],
                                           "cpu": 0.5, "memory": "512MiB", "restart": "always"}]}))
    text = node_unit(inv.software.run[0], "d1")
    assert 'ExecStart=/usr/local/lib/ccrp/ros-run "python3" "-m" "pkg.node" "--name=$$X"' in text
    assert "User=ros" in text and "CPUQuota=50%" in text and "MemoryMax=536870912" in text and "Restart=always" in text


def test_node_files_restart_only_what_changed():
    inv = inventory(lab(software={"run": [{"name": "a", "command": ["a"]}, {"name": "b", "command": ["b"]}]}))
    files = node_files(inv, inv.robots[0], "s1")
    assert [f.dest for f in files] == ["/etc/systemd/system/ccrp-run-a.service", "/etc/systemd/system/ccrp-run-b.service", INDEX]
    assert json.loads(files[-1].content)["nodes"].keys() == {"a", "b"}

    class Clone:
        def __init__(self):
            self.pushed, self.argv = [], None

        transport = property(lambda self: self)  # a fake clone is its own transport
        def push_files(self, robot, files, restart):
            self.pushed += [f.dest for f in files]

        def exec(self, robot, argv, timeout=60):
            self.argv = argv
            return 0, ""

    import hashlib

    have = {f.dest: hashlib.sha256(f.content.encode()).hexdigest() for f in files}
    clone = Clone()
    assert apply_nodes(clone, "nao1", files, have) == [] and clone.argv is None  # all current: nothing at all
    inv2 = inventory(lab(software={"run": [{"name": "a", "command": ["a", "-v"]}, {"name": "b", "command": ["b"]}]}))
    changed = node_files(inv2, inv2.robots[0], "s1")
    assert apply_nodes(clone, "nao1", changed, have) == ["a"]
    assert clone.pushed == ["/etc/systemd/system/ccrp-run-a.service", INDEX]
    assert clone.argv[3:] == ["ccrp-nodes", "a b", "a"]  # keep a and b, restart a
    clone = Clone()
    assert node_files(inventory(lab()), inv.robots[0], "s1") == []
    apply_nodes(clone, "nao1", [], {absent_index().dest: "x"})  # it ran nodes before: all removed
    assert clone.argv[3:] == ["ccrp-nodes", ""] and f'rm -f "{INDEX}"' in clone.argv[2]


def test_nodes_leave_the_clone_when_the_inventory_drops_them(tmp_path):
    """APPLY_SH for real, against a stand-in systemctl: stale units disabled and removed."""
    from ccrp_cli.services.workloads import APPLY_SH

    units, log = tmp_path / "units", tmp_path / "calls"
    units.mkdir()
    for n in ("a", "old"):
        (units / f"ccrp-run-{n}.service").write_text("x")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "systemctl").write_text(f'#!/bin/sh\necho "$@" >> {log}\n')
    (bin_dir / "systemctl").chmod(0o755)
    script = APPLY_SH.replace("/etc/systemd/system", str(units))
    proc = subprocess.run(["sh", "-c", script, "ccrp-nodes", "a b", "b"], capture_output=True, text=True,
                          env={"PATH": f"{bin_dir}:/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in units.iterdir()) == ["ccrp-run-a.service"]
    calls = log.read_text().splitlines()
    assert calls[0] == "disable --now ccrp-run-old.service" and "daemon-reload" in calls
    assert "reset-failed ccrp-run-old.service" in calls
    assert "restart ccrp-run-b.service" in calls and "start ccrp-run-a.service" in calls


# -- status and logs ------------------------------------------------------------------------------

def test_health_reports_each_node_with_its_restarts(tmp_path, monkeypatch):
    import importlib.util

    import ccrp_cli.agent

    path = Path(ccrp_cli.agent.__file__).parent / "health.py"
    spec = importlib.util.spec_from_file_location("ccrp_health_agent", path)
    health = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(health)
    index = tmp_path / "workloads.json"
    index.write_text(json.dumps({"nodes": {"mapper": "d1", "faces": "d2"}, "software": "s"}))

    def show(argv, **kw):
        assert argv[:4] == ["systemctl", "show", "--property", "ActiveState,SubState,NRestarts"]
        out = "ActiveState=active\nSubState=running\nNRestarts=0\n\nActiveState=activating\nSubState=auto-restart\nNRestarts=7\n"
        return subprocess.CompletedProcess(argv, 0, out, "")

    monkeypatch.setattr(health.subprocess, "run", show)
    rows = health.nodes(str(index))
    assert rows == [{"name": "mapper", "state": "active", "sub": "running", "restarts": 0, "digest": "d1"},
                    {"name": "faces", "state": "activating", "sub": "auto-restart", "restarts": 7, "digest": "d2"}]
    assert health.nodes(str(tmp_path / "none.json")) is None
    from ccrp_cli.alerts import clone_alerts
    from ccrp_cli.models.status import StatusRow

    row = StatusRow(robot="nao1", clone="cri-nao1", phase="ready", status="running", state="running", ros_distro="noetic",
                    common_ip="10.90.0.10", vpn_subnet="10.80.1.0/24", master_reachable=True, vpn_connected=True, nodes=rows)
    assert [a["text"] for a in clone_alerts(row) if a["kind"] == "node-failing"] == [
        "node faces on nao1's clone is activating after 7 restart(s): ccrp logs --robot nao1 faces"]


def test_logs_reads_the_journal_through_the_provider():
    inv = inventory(lab(software={"run": [{"name": "mapper", "command": ["m"]}]}))
    assert log_units(inv, inv.robots[0], None) == ["ccrp-run-mapper.service"]
    assert log_units(inv, inv.robots[0], "relay") == ["ccrp-relay.service"]
    with pytest.raises(InputError, match="neither a node"):
        log_units(inv, inv.robots[0], "nope")

    class Clone:
        argv = None

        transport = property(lambda self: self)  # a fake clone is its own transport
        def exec(self, robot, argv, timeout=60):
            self.argv = argv
            lines = [{"__CURSOR": "c1", "__REALTIME_TIMESTAMP": "1700000000000000", "_SYSTEMD_UNIT": "ccrp-run-mapper.service",
                      "MESSAGE": "ccrp_offload 1.0 started"},
                     {"__CURSOR": "c2", "__REALTIME_TIMESTAMP": "1700000001000000", "MESSAGE": [104, 105, 255]}]
            return 0, "\n".join(json.dumps(x) for x in lines) + "\nnot json\n"

    clone = Clone()
    entries, cursor = read_journal(clone, "nao1", ["ccrp-run-mapper.service"], 50, since_s=600)
    assert cursor == "c2" and entries[0]["message"] == "ccrp_offload 1.0 started" and entries[1]["message"] == "hi\ufffd"
    assert entries[0]["time"].startswith("2023-11-14T22:13:20")
    assert clone.argv[-4:] == ["--lines", "50", "--since", "-600s"]
    read_journal(clone, "nao1", ["ccrp-run-mapper.service"], 50, cursor="c2")
    assert clone.argv[-4:] == ["--after-cursor", "c2", "--lines", "50"]  # a bounded page after the cursor


def test_logs_cli_refuses_bad_input_in_one_line(tmp_path):
    for args in (["--robot", "nao1"], ["--robot", "nao1", "relay", "--since", "5q"], ["--robot", "ghost", "relay"]):
        code, out, err = run_ccrp_inprocess("logs", "-i", str(LAB), *args, home=tmp_path / "home")
        assert code == 2 and len(err.splitlines()) == 1 and err.startswith("ccrp: error: "), (args, err)
