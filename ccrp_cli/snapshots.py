"""Golden images: build from the recipe, capture a configured clone, list, delete."""

from __future__ import annotations

import datetime as dt
from typing import Callable

from .errors import CcrpError
from .fleet import Fleet
from .providers.base import SnapshotRecord

Progress = Callable[[str], None]


def _stamp() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d%H%M%S")


def image_repo(fleet: Fleet) -> str:
    return f"ccrp/{fleet.name}-clone"


def build(fleet: Fleet, provider, progress: Progress, bare: bool = False) -> SnapshotRecord:
    """Build the golden clone image (docker) and record it for new clones. A `bare` snapshot has
    only systemd and cloud-init: its clones install the recipe's packages at boot, as a clone
    started from a stock cloud image would (slower: the reason for snapshots, see bench/)."""
    from .providers.base import owner_labels
    from .providers.docker import images
    from .recipes import platform

    inv = fleet.inventory
    plat = platform(inv.ros.distro, provider.kind)
    base = inv.provider.base_image  # type: ignore[union-attr]
    client = provider.client
    if bare:
        base, plat = f"ccrp/base-bare:{inv.ros.distro}", plat.model_copy(update={"packages": images.BARE_PACKAGES, "pip": []})
        if not provider.has_image(base):
            images.build_base_image(client, base, images.BASE_PACKAGES + images.BARE_PACKAGES, progress)
    elif not provider.has_image(base):
        if base != images.DEFAULT_BASE:
            progress(f"pulling base image {base}")
            try:
                client.images.pull(base)
            except Exception as exc:  # noqa: BLE001 - registry errors vary
                raise CcrpError(f"cannot pull base image {base}: {exc}", hint="check provider.base_image") from None
        else:
            # ccrp's own base: Debian packages only, with the recipe's packages already in.
            images.build_base_image(client, base, sorted(set(images.BASE_PACKAGES + plat.packages)), progress)
    tag = f"{image_repo(fleet)}:{'bare-' if bare else ''}{_stamp()}"
    progress(f"building snapshot {tag} from {base}")
    labels = owner_labels(fleet.name, "snapshot") | {"ccrp-distro": inv.ros.distro, "ccrp-bare": str(bare).lower()}
    images.build_clone_image(client, tag, images.dockerfile(fleet.name, inv.ros.distro, base, plat), labels, progress,
                             images.build_context(plat, progress))
    record = provider.snapshot_record(client.images.get(tag))
    _use(fleet, record, bare)
    return record


def _use(fleet: Fleet, record: SnapshotRecord, bare: bool = False) -> None:
    state = fleet.store.load_state()
    state.snapshot = {"image": record.name, "id": record.id, "source": record.source}
    if bare:
        state.snapshot["bare"] = "true"
    fleet.store.save_state(state)


def create(fleet: Fleet, provider, robot: str, use: bool) -> SnapshotRecord:
    record = provider.create_snapshot(robot, f"{image_repo(fleet)}:{robot}-{_stamp()}")
    if use:
        _use(fleet, record)
    return record


def delete(fleet: Fleet, provider, snapshot: str, force: bool) -> None:
    state = fleet.store.load_state()
    current = state.snapshot or {}
    if snapshot in (current.get("image"), current.get("id")) and not force:
        raise CcrpError(f"snapshot {snapshot} is the one new clones are created from", hint="pass --force to delete it anyway")
    provider.delete_snapshot(snapshot)
    if snapshot in (current.get("image"), current.get("id")):
        state.snapshot = None
        fleet.store.save_state(state)
