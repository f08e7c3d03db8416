"""GCE snapshots: images of a clone's (or the builder's) boot disk, labelled as the fleet's; and
whether an image path resolves (a fleet's snapshot, or a public family such as Debian's)."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_ROBOT, LABEL_ROLE, SnapshotRecord, owner_labels
from .ownership import gce_name, request_id


class Images:
    """Mixed into GcpProvider: the calls it makes are the provider's (self._call, self.c...)."""

    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        """An image of the clone's boot disk (taken while it runs), labelled as the fleet's snapshot."""
        with self._errors(f"snapshot of clone {robot}"):
            _zone, inst = self._require(robot)
            disk = next(d.source for d in inst.disks if d.boot)
            # A builder's image is a build, not a robot's clone: no robot label, source "build".
            source = robot if inst.labels.get(LABEL_ROLE) == "clone" else None
            image = self.compute.Image(name=gce_name(name), source_disk=disk,
                                       labels=owner_labels(self.fleet, "snapshot", source))
            self._mutate(f"create image {image.name}", self.c.images.insert, request=self.compute.InsertImageRequest(
                project=self.project, image_resource=image, force_create=True,
                request_id=request_id(self.fleet, "image", image.name)))
            return self._snapshot_record(self._call("get image", self.c.images.get, project=self.project,
                                                    image=image.name))

    @staticmethod
    def _snapshot_record(image) -> SnapshotRecord:
        return SnapshotRecord(
            id=str(image.id), name=image.name, created=image.creation_timestamp[:19],
            source=dict(image.labels).get(LABEL_ROBOT) or "build",
            size_mb=round(image.archive_size_bytes / 1e6, 1) if image.archive_size_bytes else None)

    def _images(self) -> list:
        request = self.compute.ListImagesRequest(project=self.project, filter=self.names.label_filter("snapshot"))
        return [i for i in self._list("images", self.c.images.list, request=request)
                if self.names.owns_labels(i.labels)]

    def list_snapshots(self) -> list[SnapshotRecord]:
        with self._errors("list snapshots"):
            return sorted((self._snapshot_record(i) for i in self._images()), key=lambda s: s.created)

    def has_image(self, image: str) -> bool:
        """A snapshot of the fleet by name or id, or an image path GCE resolves (a public family)."""
        if any(image in (s.id, s.name) for s in self.list_snapshots()):
            return True
        project, _, rest = image.partition("projects/")[2].partition("/global/images/")
        if not (project and rest):
            return False
        with self._errors(f"look up image {image}"):
            if rest.startswith("family/"):
                found = self._get("image family", self.c.images.get_from_family, project=project, family=rest[7:])
            else:
                found = self._get("image", self.c.images.get, project=project, image=rest)
        return found is not None

    def delete_snapshot(self, snapshot_id: str) -> None:
        with self._errors(f"delete snapshot {snapshot_id}"):
            image = next((i for i in self._images() if snapshot_id in (str(i.id), i.name)), None)
            if image is None:
                raise CcrpError(f"no snapshot {snapshot_id} of fleet {self.fleet} in {self.project}",
                                hint="ccrp snapshot list")
            self._wait_all([("delete image", self._delete("image", self.c.images.delete, project=self.project,
                                                          image=image.name))])
