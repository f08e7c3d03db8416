"""The registry of backends: each package's ProviderInfo (abilities, user-data limit, SDK modules,
platform), which costs no SDK import. The loader validates the inventory's `provider:` section with
the settings class it holds for the section's kind; this module knows nothing of the inventory
(providers/__init__.py get_provider does)."""

from __future__ import annotations

from .aws import INFO as _AWS
from .base import Ability, ProviderInfo
from .docker import INFO as _DOCKER
from .gcp import INFO as _GCP
from .libvirt import INFO as _LIBVIRT
from .openstack import INFO as _OPENSTACK
from ..errors import InputError

REGISTRY: dict[str, ProviderInfo] = {}


def declare(backend: ProviderInfo) -> None:
    """Hold `backend`, and tell its settings class what the inventory asks of it (models/ imports
    no provider: ProviderSettings.platform and .bakes)."""
    backend.settings.platform = backend.platform  # type: ignore[attr-defined]
    backend.settings.bakes = Ability.BAKE in backend.abilities  # type: ignore[attr-defined]
    backend.settings.gateways = Ability.ENTRY_GATEWAY in backend.abilities  # type: ignore[attr-defined]
    REGISTRY[backend.kind] = backend


for _backend in (_DOCKER, _OPENSTACK, _GCP, _AWS, _LIBVIRT):
    declare(_backend)


def kinds(conjunction: str = "or") -> str:
    """The backends' kinds for a message: "docker, openstack, gcp, aws or libvirt"."""
    names = list(REGISTRY)
    return ", ".join(names[:-1]) + f" {conjunction} {names[-1]}" if len(names) > 1 else "".join(names)


def info(kind: str) -> ProviderInfo:
    return REGISTRY[kind]


def require(kind: str, ability: Ability, hint: str) -> None:
    """Exit 2 with one line, before any SDK is loaded, when the backend cannot do what a command needs."""
    if ability not in REGISTRY[kind].abilities:
        raise InputError(f"the {kind} provider cannot do {ability.value}", hint=hint)
