"""Backends behind one lifecycle interface (base.Provider). Each package declares a ProviderInfo
(abilities, user-data limit, SDK modules, platform) that costs no SDK import (registry.py); the
provider class, and its SDK, are imported only when a provider is made, with an install hint when
missing."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING

from ..store import FleetStore
from .base import Ability, Provider
from .registry import REGISTRY, info, require

if TYPE_CHECKING:
    # For the annotation only: models/inventory.py imports registry.py, which runs this package's
    # __init__ first, while the inventory module is still half-made.
    from ..models.inventory import Inventory

__all__ = ["REGISTRY", "Ability", "get_provider", "info", "require"]


def get_provider(inv: Inventory, workdir: Path | None = None) -> Provider:
    module, cls = REGISTRY[inv.provider.kind].factory.split(":")
    backend = getattr(importlib.import_module(f"{__name__}.{module}"), cls)
    return backend(inv, workdir or FleetStore(inv.fleet).root)
