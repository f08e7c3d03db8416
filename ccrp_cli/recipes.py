"""Golden-image recipes from snapshots/<distro>.yaml."""

from __future__ import annotations

from functools import cache

import yaml
from pydantic import BaseModel, ConfigDict

from .errors import InputError
from .providers import REGISTRY
from .resources import data_dir


class Platform(BaseModel):
    """What a clone image holds beyond its base: packages from the distribution's own archive
    (no third-party apt source) and the clone agents' Python packages."""

    model_config = ConfigDict(extra="forbid")
    packages: list[str]
    # Python packages for the clone's agents (the relay's Zenoh), installed with the system pip.
    pip: list[str] = []


class Recipe(BaseModel):
    model_config = ConfigDict(extra="forbid")
    distro: str
    platforms: dict[str, Platform]


# Which platform each provider's clones run, as each backend declares it (ProviderInfo.platform):
# debian-bookworm on all four, so a clone behaves the same on every backend. Debian 12 ships
# OpenVPN 2.6, which the rendered server.conf needs (data-ciphers); Ubuntu 20.04's OpenVPN 2.4
# refuses it, which is why no focal platform exists any more.
PROVIDER_PLATFORM = {kind: info.platform for kind, info in REGISTRY.items()}


@cache
def recipe(distro: str) -> Recipe:
    path = data_dir("snapshots") / f"{distro}.yaml"
    if not path.exists():
        raise InputError(f"no snapshot recipe for ROS distro {distro!r} ({path})")
    return Recipe.model_validate(yaml.safe_load(path.read_text()))


def platform(distro: str, provider: str) -> Platform:
    return recipe(distro).platforms[PROVIDER_PLATFORM[provider]]
