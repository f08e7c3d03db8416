"""Backends behind one lifecycle interface (base.Provider). SDKs are imported lazily: each
provider package imports its SDK only when constructed, with an install hint when missing."""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ..models.inventory import Inventory
    from .base import Provider

# kind -> (module, class); the clouds take the fleet's store root (SSH key, pinned host keys).
_BACKENDS = {
    "docker": ("docker", "DockerProvider"),
    "openstack": ("openstack", "OpenStackProvider"),
    "gcp": ("gcp", "GcpProvider"),
    "aws": ("aws", "AwsProvider"),
}


def get_provider(inv: "Inventory", workdir: Path | None = None) -> "Provider":
    module, cls = _BACKENDS[inv.provider.kind]
    backend = getattr(importlib.import_module(f"{__name__}.{module}"), cls)
    if inv.provider.kind == "docker":
        return backend(inv)
    from ..store import FleetStore

    return backend(inv, workdir or FleetStore(inv.fleet).root)
