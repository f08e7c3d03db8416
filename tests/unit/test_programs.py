"""A node's program is on its clone, or the inventory is refused in one line before anything changes
(services/programs.py; docs/workloads.md, ROS habits). Judged against the recipe's `programs:`
(snapshots/<distro>.yaml), the fleet's apt packages and the workspace's console scripts."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from ccrp_cli.errors import InputError
from ccrp_cli.fleet import Fleet
from ccrp_cli.loader import parse_inventory
from ccrp_cli.ops import deploy
from ccrp_cli.recipes import Platform, platform
from ccrp_cli.services import programs
from ccrp_cli.services.workloads import snapshot_software
from tests.conftest import LAB
from tests.inprocess_cli import run_ccrp_inprocess

ROS1_TOOLS = ["rosrun", "roslaunch", "rostopic", "rosnode", "rosparam", "rosservice", "rosbag", "roscore", "rosmsg"]
SETUP_PY = """from setuptools import setup
setup(name="offload", entry_points={"console_scripts": ["scan_to_map = offload.scan:main", "other=offload.o:run"]})
"""


def lab(run: list, distro: str = "noetic", **software) -> dict:
    data = yaml.safe_load(LAB.read_text())
    data.pop("services", None)
    for robot in data["robots"]:
        robot.pop("services", None)
    data["ros"] = {"distro": distro}
    data["software"] = {"run": [{"name": f"n{i}", "command": cmd} for i, cmd in enumerate(run)], **software}
    return data


def judge(data: dict, where: Path | None = None) -> list[str]:
    """snapshot_software's check (it raises), then the warnings validate prints."""
    inv = parse_inventory(data, "inventory.yaml")
    software = snapshot_software(inv, (where or Path("/nonexistent")) / "inventory.yaml")
    return programs.check(inv, software.apt, software.workspace)


def without(monkeypatch, package: str) -> None:
    """The Noetic recipe as if its image lacked `package` (the other check: apt adds it back)."""
    real = platform("noetic", "debian-bookworm")
    fake = Platform.model_validate({**real.model_dump(), "packages": [p for p in real.packages if p != package],
                                    "implied": [p for p in real.implied if p != package]})
    monkeypatch.setattr(programs, "platform", lambda distro, name: fake if distro == "noetic" else platform(distro, name))


@pytest.mark.parametrize("tool", ROS1_TOOLS)
def test_each_ros1_tool_is_on_a_noetic_clone(tool):
    assert judge(lab([[tool, "my_pkg", "x"]])) == []


@pytest.mark.parametrize("tool", ROS1_TOOLS)
def test_each_ros1_tool_without_its_package_is_refused_naming_it(monkeypatch, tool):
    package = platform("noetic", "debian-bookworm").programs[tool]
    without(monkeypatch, package)
    with pytest.raises(InputError) as refused:
        judge(lab([["python3", "-m", "a.b"], [tool, "my_pkg", "x"]]))
    line = refused.value.one_line()
    assert f"software.run n1: {tool!r} is not on the clone: Debian's package {package} has it" in line, line
    assert f"add {package} to software.apt" in line and "\n" not in line
    assert judge(lab([[tool, "my_pkg", "x"]], apt=[package])) == []  # named under apt: on the clone


def test_a_program_of_a_package_the_image_lacks_is_refused_at_any_level():
    data = lab([])
    data["robots"][1]["software"] = {"run": [{"name": "old", "command": ["python", "node.py"]}]}
    with pytest.raises(InputError) as refused:
        judge(data)
    assert f"robots[{data['robots'][1]['name']}].software.run old: 'python'" in str(refused.value)
    assert "python-is-python3" in refused.value.one_line()
    data["types"] = {"nao": {"software": {"apt": ["python-is-python3"]}}}
    assert judge(data) == []


def test_a_path_is_left_to_run_and_an_unknown_bare_name_is_a_warning():
    assert judge(lab([["/opt/ccrp/workspace/lib/my_pkg/my_node"], ["./bin/tool"]])) == []
    [warning] = judge(lab([["my-mapper", "--fast"]]))
    assert warning.startswith("software.run n0: 'my-mapper' is no program ccrp knows on the clone (ROS noetic")
    assert "software.apt" in warning
    assert judge(lab([["htop"]], apt=["htop"])) == []  # a package named as its program


def test_a_workspace_console_script_is_known(tmp_path):
    pkg = tmp_path / "ws" / "src" / "offload"
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text(
        '<?xml version="1.0"?><package format="3"><name>offload</name><version>1.0.0</version><description>x'
        '</description><maintainer email="a@b.c">a</maintainer><license>MIT</license>'
        '<export><build_type>ament_python</build_type></export></package>')
    (pkg / "setup.py").write_text(SETUP_PY)
    data = lab([["scan_to_map"], ["other", "--x"]], distro="jazzy", workspace="ws")
    assert judge(data, tmp_path) == []
    (pkg / "setup.py").write_text("from setuptools import setup\nsetup(name='offload')\n")
    (pkg / "setup.cfg").write_text("[options.entry_points]\nconsole_scripts =\n    scan_to_map = offload.scan:main\n")
    assert [w.split(":")[0] for w in judge(data, tmp_path)] == ["software.run n1"]  # only `other` unknown now


def test_ros2_is_refused_on_the_wheels_with_what_to_write_instead():
    with pytest.raises(InputError) as refused:
        judge(lab([["ros2", "run", "my_pkg", "node"]], distro="jazzy"))
    line = refused.value.one_line()
    assert "software.run n0: 'ros2': the ROS 2 wheels have no ros2 CLI" in line and "[python3, -m, " in line, line
    assert judge(lab([["python3", "-m", "my_pkg.node"]], distro="jazzy")) == []
    # ROS's own apt packages (a cloud image of the user's with ros-jazzy-ros-base) have it.
    assert "ros2" in platform("jazzy", "ubuntu-noble-ros").programs


def test_fleet_validate_and_plan_refuse_in_one_line(tmp_path, ccrp_home):
    path = tmp_path / "inventory.yaml"
    path.write_text(yaml.safe_dump(lab([["ros2", "launch", "my_pkg", "x.launch.py"]], distro="jazzy")))
    for command in (["fleet", "validate"], ["fleet", "plan"]):
        code, out, err = run_ccrp_inprocess(*command, "-i", str(path), home=ccrp_home)
        assert code == 2 and out == "" and len(err.strip().splitlines()) == 1, (command, code, out, err)
        assert "'ros2': the ROS 2 wheels have no ros2 CLI" in err, err
    path.write_text(yaml.safe_dump(lab([["my-mapper"], ["rosrun", "my_pkg", "n.py"]])))
    code, out, err = run_ccrp_inprocess("fleet", "validate", "-i", str(path), home=ccrp_home)
    assert code == 0 and "is valid" in err and "warning: software.run n0: 'my-mapper' is no program" in err, err
    assert "rosrun" not in err


def test_deploy_refuses_before_anything(tmp_path, ccrp_home, monkeypatch):
    path = tmp_path / "inventory.yaml"
    path.write_text(yaml.safe_dump(lab([["rosrun", "my_pkg", "n.py"]])))
    without(monkeypatch, "rosbash")

    class Untouched:
        kind = "docker"

        def __getattr__(self, name):
            raise AssertionError(f"deploy asked the provider for {name} before refusing")

    with pytest.raises(InputError, match="'rosrun' is not on the clone: Debian's package rosbash has it"):
        deploy.deploy(Fleet.open(path), Untouched(), lambda m: None)
