"""GCE snapshots: images of a clone's (or the builder's) boot disk, labelled as the fleet's; and
whether an image path resolves (a fleet's snapshot, or a public family such as Debian's)."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_ROBOT, LABEL_ROLE, SnapshotRecord, owner_labels
from .client import GcpClient
from .ownership import gce_name, request_id


def create_snapshot(c: GcpClient, robot: str, name: str) -> SnapshotRecord:
    """An image of the clone's boot disk (taken while it runs), labelled as the fleet's snapshot."""
    with c.errors(f"snapshot of clone {robot}"):
        _zone, inst = c.require(robot)
        disk = next(d.source for d in inst.disks if d.boot)
        # A builder's image is a build, not a robot's clone: no robot label, source "build".
        source = robot if inst.labels.get(LABEL_ROLE) == "clone" else None
        image = c.compute.Image(name=gce_name(name), source_disk=disk,
                                   labels=owner_labels(c.fleet, "snapshot", source))
        c.mutate(f"create image {image.name}", c.clients.images.insert, request=c.compute.InsertImageRequest(
            project=c.project, image_resource=image, force_create=True,
            request_id=request_id(c.fleet, "image", image.name)))
        return snapshot_record(c.call("get image", c.clients.images.get, project=c.project,
                                                image=image.name))


def snapshot_record(image) -> SnapshotRecord:
    return SnapshotRecord(
        id=str(image.id), name=image.name, created=image.creation_timestamp[:19],
        source=dict(image.labels).get(LABEL_ROBOT) or "build",
        size_mb=round(image.archive_size_bytes / 1e6, 1) if image.archive_size_bytes else None)


def owned_images(c: GcpClient) -> list:
    request = c.compute.ListImagesRequest(project=c.project, filter=c.names.label_filter("snapshot"))
    return [i for i in c.list("images", c.clients.images.list, request=request)
            if c.names.owns_labels(i.labels)]


def list_snapshots(c: GcpClient) -> list[SnapshotRecord]:
    with c.errors("list snapshots"):
        return sorted((snapshot_record(i) for i in owned_images(c)), key=lambda s: s.created)


def has_image(c: GcpClient, image: str) -> bool:
    """A snapshot of the fleet by name or id, or an image path GCE resolves (a public family)."""
    if any(image in (s.id, s.name) for s in list_snapshots(c)):
        return True
    project, _, rest = image.partition("projects/")[2].partition("/global/images/")
    if not (project and rest):
        return False
    with c.errors(f"look up image {image}"):
        if rest.startswith("family/"):
            found = c.get("image family", c.clients.images.get_from_family, project=project, family=rest[7:])
        else:
            found = c.get("image", c.clients.images.get, project=project, image=rest)
    return found is not None


def delete_snapshot(c: GcpClient, snapshot_id: str) -> None:
    with c.errors(f"delete snapshot {snapshot_id}"):
        image = next((i for i in owned_images(c) if snapshot_id in (str(i.id), i.name)), None)
        if image is None:
            raise CcrpError(f"no snapshot {snapshot_id} of fleet {c.fleet} in {c.project}",
                            hint="ccrp snapshot list")
        c.wait_all([("delete image", c.delete("image", c.clients.images.delete, project=c.project,
                                                      image=image.name))])
