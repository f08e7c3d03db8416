"""Backends behind one lifecycle interface (base.Provider). Each package declares a ProviderInfo
(abilities, user-data limit, SDK modules, platform) that costs no SDK import; the provider class,
and its SDK, are imported only when a provider is made, with an install hint when missing."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING

from .aws import INFO as _AWS
from .base import Ability, ProviderInfo
from .docker import INFO as _DOCKER
from .gcp import INFO as _GCP
from .libvirt import INFO as _LIBVIRT
from .openstack import INFO as _OPENSTACK

if TYPE_CHECKING:
    from ..models.inventory import Inventory
    from .base import Provider

REGISTRY: dict[str, ProviderInfo] = {i.kind: i for i in (_DOCKER, _OPENSTACK, _GCP, _AWS, _LIBVIRT)}


def info(kind: str) -> ProviderInfo:
    return REGISTRY[kind]


def require(kind: str, ability: Ability, hint: str) -> None:
    """Exit 2 with one line, before any SDK is loaded, when the backend cannot do what a command needs."""
    from ..errors import InputError

    if ability not in REGISTRY[kind].abilities:
        raise InputError(f"the {kind} provider cannot do {ability.value}", hint=hint)


def get_provider(inv: "Inventory", workdir: Path | None = None) -> "Provider":
    module, cls = REGISTRY[inv.provider.kind].factory.split(":")
    backend = getattr(importlib.import_module(f"{__name__}.{module}"), cls)
    from ..store import FleetStore

    return backend(inv, workdir or FleetStore(inv.fleet).root)
