"""OpenStack snapshots: Glance images of a clone's (or the builder's) server, labelled as the fleet's."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_FLEET, LABEL_ROBOT, LABEL_ROLE, SnapshotRecord, owner_labels


class Images:
    """Mixed into OpenStackProvider: the calls it makes are the provider's (self.api, self.image...)."""

    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        """A Glance image of the clone's server, with the labels as properties and tags."""
        with self._errors(f"snapshot of {robot}"):
            server = self._running_server(robot)
            # A builder's image is a build, not a robot's clone: no robot label, source "build".
            source = robot if (server.metadata or {}).get(LABEL_ROLE) == "clone" else None
            labels = owner_labels(self.fleet, "snapshot", source)
            image = self.api("create server image", self.compute.create_server_image, server, name, metadata=labels)
            try:
                for tag in self.tags("snapshot", source):
                    self.api("tag image", self.image.add_tag, image, tag)
                image = self.api("wait for image", self.image.wait_for_status, image, status="active",
                                 failures=["killed", "deleted", "deactivated"], interval=self.poll_interval,
                                 wait=self.image_timeout)
            except BaseException:
                self._rollback([("image", image)])
                raise
            return self._snapshot_record(image)

    def _snapshot_record(self, image) -> SnapshotRecord:
        props = image.properties or {}
        return SnapshotRecord(id=image.id, name=image.name or "", created=(image.created_at or "")[:19],
                              source=props.get(LABEL_ROBOT) or "build",
                              size_mb=round(image.size / 1e6, 1) if image.size else None)

    def _images(self) -> list:
        found = self.listing("images", self.image.images, tag=f"{LABEL_FLEET}={self.fleet}")
        return [i for i in found if self._is_owned(i.properties)]

    def list_snapshots(self) -> list[SnapshotRecord]:
        with self._errors("list snapshots"):
            return sorted((self._snapshot_record(i) for i in self._images()), key=lambda s: s.created)

    def delete_snapshot(self, snapshot_id: str) -> None:
        with self._errors(f"delete snapshot {snapshot_id}"):
            image = self.find("image", self.image.find_image, snapshot_id)
            if image is None:
                raise CcrpError(f"snapshot {snapshot_id} not found", hint="ccrp snapshot list")
            if not self._is_owned(image.properties):
                raise CcrpError(f"image {snapshot_id} is not a snapshot of fleet {self.fleet!r}")
            self.api("delete image", self.image.delete_image, image)

    def has_image(self, image: str) -> bool:
        return self.find("image", self.image.find_image, image) is not None
