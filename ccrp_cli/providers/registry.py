"""The registry of backends: each package's ProviderInfo (abilities, user-data limit, SDK modules,
platform), which costs no SDK import. The inventory builds its `provider:` union from it, so this
module knows nothing of the inventory (providers/__init__.py get_provider does)."""

from __future__ import annotations

from .aws import INFO as _AWS
from .base import Ability, ProviderInfo
from .docker import INFO as _DOCKER
from .gcp import INFO as _GCP
from .libvirt import INFO as _LIBVIRT
from .openstack import INFO as _OPENSTACK
from ..errors import InputError

REGISTRY: dict[str, ProviderInfo] = {i.kind: i for i in (_DOCKER, _OPENSTACK, _GCP, _AWS, _LIBVIRT)}


def info(kind: str) -> ProviderInfo:
    return REGISTRY[kind]


def require(kind: str, ability: Ability, hint: str) -> None:
    """Exit 2 with one line, before any SDK is loaded, when the backend cannot do what a command needs."""
    if ability not in REGISTRY[kind].abilities:
        raise InputError(f"the {kind} provider cannot do {ability.value}", hint=hint)
