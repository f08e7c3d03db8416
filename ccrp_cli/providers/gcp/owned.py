"""GCE: everything the fleet owns (labelled instances and images; routes, reserved addresses,
firewalls, subnetworks and networks marked in their description), deleting it, and `fleet down`'s teardown in order."""

from __future__ import annotations

from typing import Any

from ...errors import CcrpError
from ..base import LABEL_ROBOT, OwnedResource, Role, with_roles
from . import images
from .client import GcpClient
from .ownership import description_marks

# Teardown order: what points at an instance goes first, the network it lives on last.
# An address is released once its instance is gone (GCE refuses while it is in use).
TEARDOWN_ORDER = ("route", "instance", "address", "firewall", "subnet", "network")
SNAPSHOT_KINDS = ("image",)  # survive `fleet down`, as Docker snapshot images do
# What each kind is to the fleet (`ccrp gc`); routes and addresses belong to a robot.
ROLES = {"instance": Role.CLONE, "image": Role.IMAGE, "firewall": Role.BOOTSTRAP, "subnet": Role.BOOTSTRAP,
         "network": Role.BOOTSTRAP}


def marked(c: GcpClient) -> list[tuple[OwnedResource, str | None]]:
    """(resource, zone) for everything carrying the fleet's marks."""
    owned: list[tuple[OwnedResource, str | None]] = []
    for zone, inst in c.instances():
        owned.append((OwnedResource(kind="instance", id=str(inst.id), name=inst.name,
                                    robot=dict(inst.labels).get(LABEL_ROBOT)), zone))
    for image in images.owned_images(c):
        owned.append((OwnedResource(kind="image", id=str(image.id), name=image.name,
                                    robot=dict(image.labels).get(LABEL_ROBOT)), None))
    unlabelled: tuple[tuple[str, Any, dict[str, str]], ...] = (
        ("route", c.clients.routes.list, {}),
        ("address", c.clients.addresses.list, {"region": c.region}),
        ("firewall", c.clients.firewalls.list, {}),
        ("subnet", c.clients.subnetworks.list, {"region": c.region}),
        ("network", c.clients.networks.list, {}),
    )
    for kind, method, where in unlabelled:
        for item in c.list(f"{kind}s", method, project=c.project, **where):
            if c.names.owns_unlabelled(item.name, item.description):
                robot = description_marks(item.description).get(LABEL_ROBOT)
                owned.append((OwnedResource(kind=kind, id=str(item.id), name=item.name, robot=robot), None))
    return owned


def list_owned(c: GcpClient) -> list[OwnedResource]:
    with c.errors("list owned resources"):
        return with_roles((res for res, _zone in marked(c)), ROLES)


def start_delete(c: GcpClient, res: OwnedResource, zone: str | None):
    where: dict[str, tuple[Any, dict[str, str | None]]] = {
        "route": (c.clients.routes.delete, {"route": res.name}),
        "instance": (c.clients.instances.delete, {"zone": zone, "instance": res.name}),
        "address": (c.clients.addresses.delete, {"region": c.region, "address": res.name}),
        "firewall": (c.clients.firewalls.delete, {"firewall": res.name}),
        "subnet": (c.clients.subnetworks.delete, {"region": c.region, "subnetwork": res.name}),
        "network": (c.clients.networks.delete, {"network": res.name}),
        "image": (c.clients.images.delete, {"image": res.name}),
    }
    method, args = where[res.kind]
    return (f"delete {res.kind} {res.name}", c.delete(f"{res.kind} {res.name}", method,
                                                          project=c.project, **args))


def delete_owned(c: GcpClient, resource: OwnedResource) -> None:
    """Delete one owned resource; it is looked up again so nothing unowned is ever touched."""
    with c.errors(f"delete {resource.kind} {resource.name}"):
        match = next(((r, z) for r, z in marked(c) if (r.kind, r.id) == (resource.kind, resource.id)), None)
        if match is None:
            raise CcrpError(f"{resource.kind} {resource.name or resource.id} is not owned by fleet {c.fleet}")
        c.wait_all([start_delete(c, *match)])


def teardown(c: GcpClient) -> list[str]:
    """Delete everything the fleet owns except its snapshots, in dependency order; deletes of
    one kind run together (a GCE delete takes tens of seconds)."""
    removed: list[str] = []
    with c.errors(f"teardown of fleet {c.fleet}"):
        owned = marked(c)
        for kind in TEARDOWN_ORDER:
            batch = [(r, z) for r, z in owned if r.kind == kind]
            c.wait_all([start_delete(c, r, z) for r, z in batch])
            removed += [f"{r.kind} {r.name}" for r, _z in batch]
    c.subnet_link = None
    return removed


def leftovers(c: GcpClient) -> list[str]:
    """What `fleet down` should have removed and did not."""
    return [f"{r.kind} {r.name}" for r in list_owned(c) if r.kind not in SNAPSHOT_KINDS]
