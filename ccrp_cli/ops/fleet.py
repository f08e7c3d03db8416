"""The fleet verbs, each whole (PKI, fleet lock, snapshot, reconcile, the result): `ccrp fleet
up`, `scale` and `down`, and the dashboard's Scale button. reconcile.py converges the clones;
these add what a user's command needs around it. docs/architecture.md "Code map"."""

from __future__ import annotations

from typing import TYPE_CHECKING

from . import reconcile
from .snapshots import ensure_snapshot
from .vpn import ensure_pki

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Provider
    from .clones import CloneResult, Progress


def fleet_up(fleet: Fleet, provider: Provider, say: Progress) -> list[CloneResult]:
    """`ccrp fleet up`: create or reuse every robot's clone (the PKI and the snapshot first if the fleet has none)."""
    ensure_pki(fleet, say)
    with fleet.store.lock():
        ensure_snapshot(fleet, provider, say)
        return reconcile.up(fleet, provider, say)


def fleet_down(fleet: Fleet, provider: Provider, say: Progress) -> list[str]:
    """`ccrp fleet down`: remove what ccrp created for the fleet (PKI and state stay)."""
    with fleet.store.lock():
        return reconcile.down(fleet, provider, say)


def fleet_scale(fleet: Fleet, provider: Provider, size: int, say: Progress) -> list[CloneResult]:
    """`ccrp fleet scale SIZE`: grow or shrink the fleet with template robots."""
    kept, new, _removed = reconcile.scaled(fleet, fleet.store.load_state(), size)  # bad input makes no PKI, no snapshot
    ensure_pki(fleet, say)
    with fleet.store.lock():
        ensure_snapshot(fleet, provider, say, robots=kept + new)
        return reconcile.scale(fleet, provider, size, say)
