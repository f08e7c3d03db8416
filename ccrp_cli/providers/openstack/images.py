"""OpenStack snapshots: Glance images of a clone's (or the builder's) server, labelled as the fleet's."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_FLEET, LABEL_ROBOT, LABEL_ROLE, SnapshotRecord, owner_labels
from .client import OpenStackClient


def create_snapshot(c: OpenStackClient, robot: str, name: str) -> SnapshotRecord:
    """A Glance image of the clone's server, with the labels as properties and tags."""
    with c.errors(f"snapshot of {robot}"):
        server = c.running_server(robot)
        # A builder's image is a build, not a robot's clone: no robot label, source "build".
        source = robot if (server.metadata or {}).get(LABEL_ROLE) == "clone" else None
        labels = owner_labels(c.fleet, "snapshot", source)
        image = c.api("create server image", c.compute.create_server_image, server, name, metadata=labels)
        try:
            for tag in c.tags("snapshot", source):
                c.api("tag image", c.image.add_tag, image, tag)
            image = c.api("wait for image", c.image.wait_for_status, image, status="active",
                          failures=["killed", "deleted", "deactivated"], interval=c.poll_interval,
                          wait=c.image_timeout)
        except BaseException:
            try:  # what this attempt made must not linger; the failure is the one to report
                c.api("delete image", c.image.delete_image, image.id, ignore_missing=True)
            except Exception:  # noqa: BLE001
                pass
            raise
        return snapshot_record(image)


def snapshot_record(image) -> SnapshotRecord:
    props = image.properties or {}
    return SnapshotRecord(id=image.id, name=image.name or "", created=(image.created_at or "")[:19],
                          source=props.get(LABEL_ROBOT) or "build",
                          size_mb=round(image.size / 1e6, 1) if image.size else None)


def owned_images(c: OpenStackClient) -> list:
    found = c.listing("images", c.image.images, tag=f"{LABEL_FLEET}={c.fleet}")
    return [i for i in found if c.is_owned(i.properties)]


def list_snapshots(c: OpenStackClient) -> list[SnapshotRecord]:
    with c.errors("list snapshots"):
        return sorted((snapshot_record(i) for i in owned_images(c)), key=lambda s: s.created)


def delete_snapshot(c: OpenStackClient, snapshot_id: str) -> None:
    with c.errors(f"delete snapshot {snapshot_id}"):
        image = c.find("image", c.image.find_image, snapshot_id)
        if image is None:
            raise CcrpError(f"snapshot {snapshot_id} not found", hint="ccrp snapshot list")
        if not c.is_owned(image.properties):
            raise CcrpError(f"image {snapshot_id} is not a snapshot of fleet {c.fleet!r}")
        c.api("delete image", c.image.delete_image, image)


def has_image(c: OpenStackClient, image: str) -> bool:
    return c.find("image", c.image.find_image, image) is not None
