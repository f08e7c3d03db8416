"""Golden-image recipes from snapshots/<distro>.yaml."""

from __future__ import annotations

from functools import cache

import yaml
from pydantic import BaseModel, ConfigDict

from .errors import InputError
from .resources import data_dir


class AptSource(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: str
    keyid: str


class Platform(BaseModel):
    model_config = ConfigDict(extra="forbid")
    packages: list[str]
    apt_sources: list[AptSource] = []
    # Python packages for the clone's agents (the relay's Zenoh), installed with the system pip.
    pip: list[str] = []
    ros_setup: str | None = None


class Recipe(BaseModel):
    model_config = ConfigDict(extra="forbid")
    distro: str
    platforms: dict[str, Platform]


# Which platform each provider's clones run.
PROVIDER_PLATFORM = {"docker": "debian-bookworm", "openstack": "ubuntu-focal", "gcp": "ubuntu-focal", "aws": "ubuntu-focal"}


@cache
def recipe(distro: str) -> Recipe:
    path = data_dir("snapshots") / f"{distro}.yaml"
    if not path.exists():
        raise InputError(f"no snapshot recipe for ROS distro {distro!r} ({path})")
    return Recipe.model_validate(yaml.safe_load(path.read_text()))


def platform(distro: str, provider: str) -> Platform:
    return recipe(distro).platforms[PROVIDER_PLATFORM[provider]]
