"""Snapshot recipes: the Jazzy recipe loads beside Noetic's; its ROS 2 layer goes into a venv, in
the plain layer and in a jazzy fleet's clone image; wheels are fetched for Debian 12's python."""

from __future__ import annotations

import secrets
import subprocess
from pathlib import Path

import pytest

from ccrp_cli.errors import InputError
from ccrp_cli.providers.docker import images, ros2, wheels
from ccrp_cli.recipes import platform, recipe


def test_jazzy_recipe_loads_beside_noetics():
    jazzy = recipe("jazzy")
    assert jazzy.distro == "jazzy" and list(recipe("noetic").platforms) == ["debian-bookworm"]
    # Jazzy also has the user's own image with ROS 2 installed (clouds only: docs/ros2.md).
    assert list(jazzy.platforms) == ["debian-bookworm", "ubuntu-noble-ros"] and jazzy.platforms["ubuntu-noble-ros"].clouds_only
    plat = platform("jazzy", "debian-bookworm")
    assert {"ros-jazzy-rclpy", "ros-jazzy-rmw-fastrtps-cpp", "ros-jazzy-std-msgs", "ros-jazzy-sensor-msgs",
            "ros-jazzy-geometry-msgs"} <= {p.split("==")[0] for p in plat.pip}
    assert "python3-venv" in plat.packages and not any(p.startswith(("ros-", "python3-rospy")) for p in plat.packages)


def test_the_distros_are_the_recipes_and_a_new_one_is_a_file(monkeypatch, tmp_path):
    """The distro list is data: snapshots/<distro>.yaml, each saying its ROS version. A recipe
    copied under a new name is a distro the inventory takes, ROS 2, whose Docker image gets the
    venv at /opt/ros/<name> and whose wheels are fetched for the tags the recipe names."""
    import shutil

    from ccrp_cli import recipes
    from ccrp_cli.loader import parse_inventory

    assert recipes.distros() == {"jazzy": 2, "kilted": 2, "noetic": 1}
    kilted = platform("kilted", "debian-bookworm")
    assert {p.split("==")[0] for p in kilted.pip} >= {"ros-kilted-rclpy", "ros-kilted-rmw-fastrtps-cpp",
                                                      "ros-kilted-std-msgs", "ros-kilted-sensor-msgs"}
    assert kilted.wheel_platforms == ["manylinux2014_x86_64", "manylinux_2_28_x86_64"]
    assert platform("noetic", "debian-bookworm").wheel_platforms == ["manylinux2014_x86_64"]
    data = tmp_path / "snapshots"
    shutil.copytree(recipes.data_dir("snapshots"), data)
    (data / "rolling.yaml").write_text((data / "kilted.yaml").read_text().replace("kilted", "rolling"))
    monkeypatch.setattr(recipes, "data_dir", lambda name: data)
    for cached in (recipes.recipe, recipes.distros):
        cached.cache_clear()
    try:
        inv = parse_inventory({"fleet": "lab", "provider": {"kind": "docker"}, "ros": {"distro": "rolling"}}, "x.yaml")
        assert inv.ros.ros2 and recipes.is_ros2("rolling") and not recipes.is_ros2("noetic")
        text = images.dockerfile("lab", "rolling", images.DEFAULT_BASE, platform("rolling", "debian-bookworm"), agents=("relay", "api_manager"))
        assert "python3 -m venv /opt/ros/rolling" in text and "ros-rolling-rclpy" in text
        (data / "bad.yaml").write_text((data / "noetic.yaml").read_text())  # names another distro inside
        recipes.distros.cache_clear()
        with pytest.raises(InputError, match="says distro 'noetic', not 'bad'"):
            recipes.distros()
    finally:
        for cached in (recipes.recipe, recipes.distros):
            cached.cache_clear()


def test_a_jazzy_clone_image_has_the_venv_in_a_stage_of_its_own(monkeypatch, tmp_path):
    plat = platform("jazzy", "debian-bookworm")
    text = images.dockerfile("lab", "jazzy", images.DEFAULT_BASE, plat, agents=("relay", "api_manager"))
    assert "FROM clone AS ros2\n" in text and "COPY --from=ros2 /opt/ros/jazzy /opt/ros/jazzy\n" in text
    assert "python3 -m venv /opt/ros/jazzy" in text and "sh /tmp/ccrp-ros2-setup /opt/ros/jazzy jazzy" in text
    # No ROS 1 agents (relay, API manager) in a ROS 2 image, and no system-wide pip install.
    assert "relay.py" not in text and "pip3 install" not in text and "cloud_init_modules" in text
    fetched = []
    monkeypatch.setenv("CCRP_CACHE", str(tmp_path))
    monkeypatch.setattr(wheels, "_pip", lambda args, what, check=True: not fetched.append(what))
    context = images.build_context(plat, distro="jazzy", agents=("relay", "api_manager"))  # none in a ROS 2 image
    assert set(context) == {"ros2-setup", "ccrp-topic"} and fetched == [["empy==3.3.4"], plat.pip]
    assert "COPY ccrp-topic /usr/local/bin/ccrp-topic" in text


def test_every_image_has_ccrp_topic_and_it_refuses_bad_usage_in_one_line():
    import sys

    assert set(images.build_context(platform("noetic", "debian-bookworm").model_copy(update={"pip": []}), agents=())) == {"ccrp-topic"}
    from tests.conftest import ROOT

    tool = str(ROOT / "templates" / "image" / "ccrp-topic")
    for argv in ([], ["bogus"], ["pub", "/chatter"], ["echo", "/a", "b", "c"], ["echo", "/a", "-n", "x"]):
        proc = subprocess.run([sys.executable, tool, *argv], capture_output=True, text=True)
        assert proc.returncode == 2 and proc.stderr.startswith("ccrp-topic: error: "), (argv, proc.stderr)
        assert "Traceback" not in proc.stderr


def test_a_jazzy_clone_image_installs_the_wheels_in_a_venv_with_a_setup_file_and_noetic_has_none():
    plat = platform("jazzy", "debian-bookworm")
    text = images.dockerfile("lab", "jazzy", images.DEFAULT_BASE, plat, agents=("relay",))
    assert "python3 -m venv /opt/ros/jazzy" in text and f"--find-links /tmp/ccrp-wheels {' '.join(plat.pip)}" in text
    assert "sh /tmp/ccrp-ros2-setup /opt/ros/jazzy jazzy" in text
    assert "venv" not in images.dockerfile("lab", "noetic", images.DEFAULT_BASE, platform("noetic", "debian-bookworm"), agents=("relay", "api_manager"))


def test_venv_context_asks_for_bookworms_python_and_builds_only_the_source_packages(monkeypatch, tmp_path):
    calls = []

    def run(argv, **kwargs):
        calls.append(argv[3:])
        return subprocess.CompletedProcess(argv, 0, "", "")

    monkeypatch.setenv("CCRP_CACHE", str(tmp_path))
    monkeypatch.setattr(wheels.subprocess, "run", run)
    zenoh_only = platform("jazzy", "debian-bookworm").model_copy(update={"pip": ["eclipse-zenoh==1.10.2"], "pip_source": []})
    assert set(ros2.venv_context(zenoh_only)) == {"ros2-setup"}
    assert [c[0] for c in calls] == ["download"]
    download = calls[0]
    assert download[download.index("--python-version") + 1] == "3.11"
    assert [download[i + 1] for i, a in enumerate(download) if a == "--platform"] == ["manylinux2014_x86_64",
                                                                                     "manylinux_2_28_x86_64"]
    calls.clear()
    ros2.venv_context(platform("jazzy", "debian-bookworm"))
    assert [c[0] for c in calls] == ["wheel", "download"] and calls[0][-1] == "empy==3.3.4"


def test_ros2_setup_lists_the_venvs_vendored_libraries_in_setup_sh(tmp_path):
    """The script both a Docker image build and a cloud's cloud-init run after installing the wheels."""
    import sys

    from tests.conftest import ROOT

    python = f"{sys.version_info[0]}.{sys.version_info[1]}"
    site = tmp_path / "lib" / f"python{python}" / "site-packages"
    for libs in ("ros_rclpy.libs", "ros_fastrtps.libs"):
        (site / libs).mkdir(parents=True)
    (tmp_path / "bin").mkdir()
    (tmp_path / "bin" / "python").symlink_to(sys.executable)
    subprocess.run(["sh", str(ROOT / "templates" / "image" / "ros2-setup"), str(tmp_path), "jazzy"], check=True)
    env = subprocess.run(["sh", "-c", '. "$0"; echo "$LD_LIBRARY_PATH|$AMENT_PREFIX_PATH|$RMW_IMPLEMENTATION"',
                          str(tmp_path / "setup.sh")], capture_output=True, text=True, check=True, env={"PATH": "/usr/bin:/bin"})
    libs, prefix, rmw = env.stdout.strip().split("|")
    assert libs.split(":") == [str(tmp_path / "lib"), str(site / "ros_fastrtps.libs"), str(site / "ros_rclpy.libs")]
    assert prefix == str(tmp_path) and rmw == "rmw_fastrtps_cpp"


def test_fetched_wheels_are_kept_and_taken_from_the_cache_the_next_time(monkeypatch, tmp_path):
    """A second fetch finds the first one's files through --find-links (pip takes a link's file
    before the index's) and gets the same bytes, so Docker's cache holds for the layer installing them."""
    monkeypatch.setenv("CCRP_CACHE", str(tmp_path / "cache"))
    calls = []

    def run(argv, **kwargs):
        calls.append(argv)
        dest = argv[argv.index("--dest") + 1] if "--dest" in argv else argv[argv.index("--wheel-dir") + 1]
        links = [argv[i + 1] for i, a in enumerate(argv) if a == "--find-links"]
        cached = [p for link in links for p in Path(link).glob("*.whl")]
        for name in ("demo-1.0-py3-none-any.whl",):
            src = next((p for p in cached if p.name == name), None)
            (Path(dest) / name).write_bytes(src.read_bytes() if src else secrets.token_bytes(16))
        return subprocess.CompletedProcess(argv, 0, "", "")

    monkeypatch.setattr(wheels.subprocess, "run", run)
    first = wheels.fetch(["demo==1.0"], ("manylinux2014_x86_64",))
    assert list(first) == ["wheels/demo-1.0-py3-none-any.whl"]
    assert (wheels.cache_dir() / "demo-1.0-py3-none-any.whl").read_bytes() == first["wheels/demo-1.0-py3-none-any.whl"]
    assert wheels.fetch(["demo==1.0"], ("manylinux2014_x86_64",)) == first
    assert str(wheels.cache_dir()) in calls[-1] and calls[-1][calls[-1].index("--python-version") + 1] == "3.11"
    assert not [p for p in wheels.cache_dir().iterdir() if p.name.startswith(".")]  # no partial copy left
