"""Backends behind one lifecycle interface (base.Provider). SDKs are imported lazily."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..errors import CcrpError

if TYPE_CHECKING:
    from ..models.inventory import Inventory
    from .base import Provider


def get_provider(inv: "Inventory") -> "Provider":
    kind = inv.provider.kind
    if kind == "docker":
        from .docker import DockerProvider

        return DockerProvider(inv)
    raise CcrpError(
        f"provider {kind!r} is not available in this version of ccrp yet",
        hint="use `kind: docker` for a local fleet",
    )
