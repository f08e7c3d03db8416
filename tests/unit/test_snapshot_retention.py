"""Snapshot retention: the newest `snapshots.keep`, plus every snapshot a clone runs from or new
clones get, stay; `gc` removes the rest too."""

from __future__ import annotations

from ccrp_cli.ops.gc import collect
from ccrp_cli.models.state import FleetState, GatewayRecord, RobotRecord
from ccrp_cli.providers.base import OwnedResource, Role, SnapshotRecord
from ccrp_cli.ops.snapshots import in_use, surplus, users


def snap(n: int) -> SnapshotRecord:
    return SnapshotRecord(id=f"sha{n}", name=f"ccrp/f-clone:{n}", created=f"2026-11-2{n}T00:00:00", source="build")


class Provider:
    def __init__(self, snapshots):
        self.snapshots = list(snapshots)
        self.deleted: list[str] = []

    def list_snapshots(self):
        return list(self.snapshots)

    def list_owned(self):
        return [OwnedResource(kind="image", id=s.id, name=s.name, role=Role.IMAGE) for s in self.snapshots]

    def delete_owned(self, resource):
        self.deleted.append(resource.id)


def state(current: int, clones: dict[str, int | None]) -> FleetState:
    return FleetState(fleet="f", snapshot={"image": f"ccrp/f-clone:{current}", "id": f"sha{current}"}, robots={
        robot: RobotRecord(index=i + 1, phase="ready", provider_id=f"c-{robot}",
                           image=None if n is None else f"sha{n}")
        for i, (robot, n) in enumerate(clones.items())})


def test_keeps_the_newest_and_what_clones_run_from():
    snaps = [snap(n) for n in range(1, 6)]
    s = state(5, {"nao1": 1, "nao2": 5})
    assert [r.id for r in surplus(s, snaps, keep=2)] == ["sha3", "sha2"]
    assert [r.id for r in surplus(s, snaps, keep=4)] == []
    used = in_use(s)
    assert users(snaps[4], used) == ["new clones", "nao2"] and users(snaps[0], used) == ["nao1"] and users(snaps[2], used) == []


def test_a_clone_of_unknown_snapshot_keeps_everything():
    snaps = [snap(n) for n in range(1, 6)]
    s = state(5, {"nao1": None, "nao2": 5})
    assert in_use(s) is None and surplus(s, snaps, keep=1) == []


def test_the_entry_gateways_snapshot_is_kept_and_one_of_unknown_snapshot_keeps_everything():
    snaps = [snap(n) for n in range(1, 6)]
    s = state(5, {"nao1": 5})
    s.gateway = GatewayRecord(provider_id="gw-1", public_ip="203.0.113.9", image="sha2")
    assert [r.id for r in surplus(s, snaps, keep=1)] == ["sha4", "sha3", "sha1"]
    assert users(snaps[1], in_use(s)) == ["entry gateway"]
    s.gateway = GatewayRecord(provider_id="gw-1", public_ip="203.0.113.9")  # found, not made by this ccrp
    assert in_use(s) is None and surplus(s, snaps, keep=1) == []


def test_gc_removes_snapshots_beyond_retention():
    provider = Provider([snap(n) for n in range(1, 5)])
    results = collect(state(4, {"nao1": 1}), provider, dry_run=False, keep=1)
    assert sorted(provider.deleted) == ["sha2", "sha3"], results
    dry = collect(state(4, {"nao1": 1}), Provider([snap(n) for n in range(1, 5)]), dry_run=True, keep=3)
    assert [r.resource.id for r in dry] == []
