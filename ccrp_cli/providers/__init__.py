"""Backends behind the protocols of base.py (Lifecycle, Images, Housekeeping: base.Provider). Each
package declares a ProviderInfo (abilities, user-data limit, SDK modules, platform) that costs no
SDK import (registry.py; register() adds one from outside ccrp_cli); the provider class, and its
SDK, are imported only when a provider is made, with an install hint when missing."""

from __future__ import annotations

import importlib
import weakref
from pathlib import Path
from typing import TYPE_CHECKING

from ..store import FleetStore
from .base import Ability, Provider, ProviderInfo
from .registry import REGISTRY, info, require

if TYPE_CHECKING:
    # For the annotation only: models/inventory.py imports registry.py, which runs this package's
    # __init__ first, while the inventory module is still half-made.
    from ..models.inventory import Inventory

__all__ = ["REGISTRY", "Ability", "close_opened", "get_provider", "info", "register", "require"]

# Every provider this process made and still holds: the CLI closes them when its command ends
# (cli/main.py run), so no command leaves an SSH session or API connection to the interpreter's
# exit. Weak: a provider a long-running process (the dashboard) dropped is not kept alive here.
_OPENED: weakref.WeakSet = weakref.WeakSet()


def get_provider(inv: Inventory, workdir: Path | None = None) -> Provider:
    module, cls = REGISTRY[inv.provider.kind].factory.split(":")
    backend = getattr(importlib.import_module(module, __name__), cls)
    provider = backend(inv, workdir or FleetStore(inv.fleet).root)
    _OPENED.add(provider)
    return provider


def close_opened() -> None:
    """Close the providers get_provider made that are still held (closing twice is harmless: the
    dashboard closes its own as it goes)."""
    for provider in list(_OPENED):
        _OPENED.discard(provider)
        try:
            provider.close()
        except Exception:  # noqa: BLE001 - the command's outcome is decided; a failed close changes nothing
            pass


def register(backend: ProviderInfo) -> None:
    """Add a backend that lives outside ccrp_cli (a test's: tests/memory_backend), as the registry's
    line adds one of ccrp's own: the inventory takes its `provider:` settings from then on."""
    from ..models.inventory import provider_union_changed

    REGISTRY[backend.kind] = backend
    provider_union_changed()


def unregister(kind: str) -> None:
    """Undo register(): the inventory refuses the backend's kind again."""
    from ..models.inventory import provider_union_changed

    del REGISTRY[kind]
    provider_union_changed()
