"""GCE: everything the fleet owns (labelled instances and images; routes, reserved addresses,
firewalls, subnetworks and networks marked in their description), deleting it, and `fleet down`'s teardown in order."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_ROBOT, OwnedResource, Role, with_roles
from .ownership import description_marks

# Teardown order: what points at an instance goes first, the network it lives on last.
# An address is released once its instance is gone (GCE refuses while it is in use).
TEARDOWN_ORDER = ("route", "instance", "address", "firewall", "subnet", "network")
SNAPSHOT_KINDS = ("image",)  # survive `fleet down`, as Docker snapshot images do
# What each kind is to the fleet (`ccrp gc`); routes and addresses belong to a robot.
ROLES = {"instance": Role.CLONE, "image": Role.IMAGE, "firewall": Role.BOOTSTRAP, "subnet": Role.BOOTSTRAP,
         "network": Role.BOOTSTRAP}


class Owned:
    """Mixed into GcpProvider: the calls it makes are the provider's (self._call, self.c...)."""

    def _owned(self) -> list[tuple[OwnedResource, str | None]]:
        """(resource, zone) for everything carrying the fleet's marks."""
        owned: list[tuple[OwnedResource, str | None]] = []
        for zone, inst in self._instances():
            owned.append((OwnedResource(kind="instance", id=str(inst.id), name=inst.name,
                                        robot=dict(inst.labels).get(LABEL_ROBOT)), zone))
        for image in self._images():
            owned.append((OwnedResource(kind="image", id=str(image.id), name=image.name,
                                        robot=dict(image.labels).get(LABEL_ROBOT)), None))
        unlabelled = (
            ("route", self.c.routes.list, {}),
            ("address", self.c.addresses.list, {"region": self.region}),
            ("firewall", self.c.firewalls.list, {}),
            ("subnet", self.c.subnetworks.list, {"region": self.region}),
            ("network", self.c.networks.list, {}),
        )
        for kind, method, where in unlabelled:
            for item in self._list(f"{kind}s", method, project=self.project, **where):
                if self.names.owns_unlabelled(item.name, item.description):
                    robot = description_marks(item.description).get(LABEL_ROBOT)
                    owned.append((OwnedResource(kind=kind, id=str(item.id), name=item.name, robot=robot), None))
        return owned

    def list_owned(self) -> list[OwnedResource]:
        with self._errors("list owned resources"):
            return with_roles((res for res, _zone in self._owned()), ROLES)

    def _start_delete(self, res: OwnedResource, zone: str | None):
        where = {
            "route": (self.c.routes.delete, {"route": res.name}),
            "instance": (self.c.instances.delete, {"zone": zone, "instance": res.name}),
            "address": (self.c.addresses.delete, {"region": self.region, "address": res.name}),
            "firewall": (self.c.firewalls.delete, {"firewall": res.name}),
            "subnet": (self.c.subnetworks.delete, {"region": self.region, "subnetwork": res.name}),
            "network": (self.c.networks.delete, {"network": res.name}),
            "image": (self.c.images.delete, {"image": res.name}),
        }
        method, args = where[res.kind]
        return (f"delete {res.kind} {res.name}", self._delete(f"{res.kind} {res.name}", method,
                                                              project=self.project, **args))

    def delete_owned(self, resource: OwnedResource) -> None:
        """Delete one owned resource; it is looked up again so nothing unowned is ever touched."""
        with self._errors(f"delete {resource.kind} {resource.name}"):
            match = next(((r, z) for r, z in self._owned() if (r.kind, r.id) == (resource.kind, resource.id)), None)
            if match is None:
                raise CcrpError(f"{resource.kind} {resource.name or resource.id} is not owned by fleet {self.fleet}")
            self._wait_all([self._start_delete(*match)])

    def teardown(self) -> list[str]:
        """Delete everything the fleet owns except its snapshots, in dependency order; deletes of
        one kind run together (a GCE delete takes tens of seconds)."""
        removed: list[str] = []
        with self._errors(f"teardown of fleet {self.fleet}"):
            owned = self._owned()
            for kind in TEARDOWN_ORDER:
                batch = [(r, z) for r, z in owned if r.kind == kind]
                self._wait_all([self._start_delete(r, z) for r, z in batch])
                removed += [f"{r.kind} {r.name}" for r, _z in batch]
        self._subnet_link = None
        return removed

    def leftovers(self) -> list[str]:
        """What `fleet down` should have removed and did not."""
        return [f"{r.kind} {r.name}" for r in self.list_owned() if r.kind not in SNAPSHOT_KINDS]
