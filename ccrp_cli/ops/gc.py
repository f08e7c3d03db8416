"""Garbage collection: resources carrying the fleet's ownership labels that state does not know.

Known are: the clones state records (a robot's provider_id, or any clone of a robot whose
creation is in flight: the next `fleet up` reuses it), what belongs to a known robot (its public
IP, volumes, routes), the bootstrap resources (network, firewall, key pair), and the fleet's
snapshots (`ccrp snapshot delete` manages those). Everything else owned is a leak: left by a crash,
an interrupted rollback or a hand-made copy.

A backend whose snapshot images live on this host (Ability.HOST_IMAGES: Docker) has them outlive
the state directory that recorded them (a quick start in a temporary CCRP_HOME, a test run): no
fleet's gc would ever see them again. `collect_images` has the backend sweep them host-wide
(HostImages.sweep_images: Docker's by the state labels each snapshot image carries).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, cast

from ..errors import CcrpError
from ..models.state import FleetState
from ..providers.base import Ability, OwnedResource, Role, SnapshotRecord

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import HostImages, Provider


@dataclass
class GcResult:
    resource: OwnedResource
    action: str  # leak | orphan | unlabelled (dry run, or not removed) | kept | deleted | failed
    detail: str = ""

    def as_dict(self) -> dict[str, Any]:
        # The role is gc's own reading; the rows show what the backend calls the resource.
        return {**self.resource.model_dump(exclude={"role"}), "action": self.action, "detail": self.detail}


def find_leaks(state: FleetState, owned: list[OwnedResource], snapshots: list[SnapshotRecord]) -> list[OwnedResource]:
    clones = {rec.provider_id for rec in state.robots.values() if rec.provider_id}
    # A robot whose clone exists or is being created: what carries its name is in use.
    live = {name for name, rec in state.robots.items() if rec.provider_id or rec.phase == "creating"}
    in_flight = {name for name, rec in state.robots.items() if rec.phase == "creating"}
    images = {s.id for s in snapshots} | {s.name for s in snapshots} | set((state.snapshot or {}).values())

    def known(r: OwnedResource) -> bool:
        if r.role is Role.BOOTSTRAP:
            return True
        if r.role is Role.CLONE:
            return r.id in clones or r.robot in in_flight
        if r.role is Role.IMAGE:
            return r.id in images or r.name in images
        if r.role is Role.ROBOT_SIDE:
            return r.robot in state.robots
        if r.role is Role.GATEWAY:  # its address is in the robots' bundles once the state has it
            return state.gateway is not None
        return r.robot in live

    return [r for r in owned if not known(r)]


def collect(state: FleetState, provider: Provider, dry_run: bool, progress: Callable[[str], None] = lambda m: None,
            keep: int = 2) -> list[GcResult]:
    """Find the fleet's leaks; unless dry_run, delete them (instances first: the rest may hang on them)."""
    from .snapshots import surplus

    snapshots = provider.list_snapshots()
    extra = {s.id for s in surplus(state, snapshots, keep)}  # beyond retention: gc removes them too
    leaks = find_leaks(state, provider.list_owned(), [s for s in snapshots if s.id not in extra])
    leaks.sort(key=lambda r: r.role is not Role.CLONE)
    if dry_run:
        return [GcResult(r, "leak") for r in leaks]
    results = []
    for r in leaks:
        try:
            provider.delete_owned(r)
            progress(f"deleted {r.kind} {r.name or r.id}")
            results.append(GcResult(r, "deleted"))
        except CcrpError as exc:
            results.append(GcResult(r, "failed", exc.one_line()))
    return results


def collect_images(provider: HostImages, dry_run: bool, unlabelled: bool = False,
                   progress: Callable[[str], None] = lambda m: None) -> list[GcResult]:
    """Ability.HOST_IMAGES: the snapshot images on this host whose state directory is gone or was
    made again (orphans), and those from before the labels (unlabelled), with what became of
    each (the backend's sweep_images says which it may remove)."""
    return [GcResult(o.resource, o.action, o.detail) for o in provider.sweep_images(dry_run, unlabelled, progress)]


def gc(fleet: Fleet, provider: Provider, dry_run: bool, unlabelled: bool,
       say: Callable[[str], None]) -> tuple[list[GcResult], list[GcResult]]:
    """`ccrp gc`: the fleet's leaked resources, and on a host that keeps the snapshot images
    (Ability.HOST_IMAGES) the orphan images, deleted unless `dry_run`: (leaks, images)."""
    if not dry_run and not fleet.store.state_path.exists():
        # Without state every owned resource looks leaked: a wrong CCRP_HOME would wipe the fleet.
        raise CcrpError(f"no state for fleet {fleet.name!r} in {fleet.store.root}: everything would count as a leak",
                        hint="run where the fleet's state lives (CCRP_HOME), `ccrp gc --dry-run` to look, or `ccrp fleet down`")
    with fleet.store.lock():  # no `fleet up` may create clones while we decide what is a leak
        leaks = collect(fleet.store.load_state(), provider, dry_run, say, fleet.inventory.snapshots.keep)
        images: list[GcResult] = []
        if Ability.HOST_IMAGES in provider.abilities:  # snapshot images live on this host, whatever their state
            images = collect_images(cast("HostImages", provider), dry_run, unlabelled, say)
    return leaks, images
