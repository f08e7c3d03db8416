"""OpenStack: everything carrying the fleet's labels (what `ccrp gc` sees), deleting it after
checking ownership on the cloud, and `fleet down`'s teardown in dependency order."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_ROBOT, OwnedResource, Role, with_roles
from . import images, network
from .client import OpenStackClient

# teardown / gc order: what depends on something is deleted before it.
ORDER = ("instance", "floating_ip", "port", "router", "subnet", "network", "security_group", "key_pair", "image")
# What each kind is to the fleet (`ccrp gc`); floating IPs and ports belong to a robot.
ROLES = {"instance": Role.CLONE, "image": Role.IMAGE, "router": Role.BOOTSTRAP, "subnet": Role.BOOTSTRAP,
         "network": Role.BOOTSTRAP, "security_group": Role.BOOTSTRAP, "key_pair": Role.BOOTSTRAP}
NEUTRON = {  # OwnedResource.kind -> Neutron collection (openstack.network proxy: list / get / delete)
    "floating_ip": ("ips", "get_ip", "delete_ip"),
    "port": ("ports", "get_port", "delete_port"),
    "router": ("routers", "get_router", "delete_router"),
    "subnet": ("subnets", "get_subnet", "delete_subnet"),
    "network": ("networks", "get_network", "delete_network"),
    "security_group": ("security_groups", "get_security_group", "delete_security_group"),
}


def list_owned(c: OpenStackClient) -> list[OwnedResource]:
    """Everything carrying the fleet's labels, in deletion order."""
    with c.errors("list owned resources"):
        found = [OwnedResource(kind="instance", id=s.id, name=s.name, robot=s.metadata.get(LABEL_ROBOT))
                 for s in c.servers()]
        for kind, (collection, _get, _delete) in NEUTRON.items():
            for res in c.tagged("fips" if collection == "ips" else collection):
                robot = next((t.split("=", 1)[1] for t in res.tags if t.startswith(f"{LABEL_ROBOT}=")), None)
                name = res.name if kind != "floating_ip" else res.floating_ip_address
                found.append(OwnedResource(kind=kind, id=res.id, name=name or "", robot=robot))
        kp = c.find("key pair", c.compute.find_keypair, c.name())
        if kp is not None and network.same_key(kp.public_key, c.operator_key()):
            found.append(OwnedResource(kind="key_pair", id=kp.name, name=kp.name))
        found += [OwnedResource(kind="image", id=i.id, name=i.name or "", robot=i.properties.get(LABEL_ROBOT))
                  for i in images.owned_images(c)]
        return with_roles(sorted(found, key=lambda r: ORDER.index(r.kind)), ROLES)


def delete_owned(c: OpenStackClient, resource: OwnedResource) -> None:
    """Delete one resource after checking, on the cloud, that it is this fleet's."""
    with c.errors(f"delete {resource.kind} {resource.id}"):
        if resource.kind == "instance":
            server = c.api("get server", c.compute.get_server, resource.id)
            owned = c.is_owned(server.metadata)
        elif resource.kind in NEUTRON:
            getter = getattr(c.network, NEUTRON[resource.kind][1])
            labels = dict(t.split("=", 1) for t in c.api(f"get {resource.kind}", getter, resource.id).tags if "=" in t)
            owned = c.is_owned(labels)
        elif resource.kind == "key_pair":
            kp = c.find("key pair", c.compute.find_keypair, resource.id)
            owned = kp is not None and resource.id == c.name() and network.same_key(kp.public_key, c.operator_key())
        elif resource.kind == "image":
            return images.delete_snapshot(c, resource.id)
        else:
            raise CcrpError(f"unknown resource kind {resource.kind!r}")
        if not owned:
            raise CcrpError(f"{resource.kind} {resource.id} is not fleet {c.fleet!r}'s; not deleting it")
        delete(c, resource, wait=True)


def delete(c: OpenStackClient, resource: OwnedResource, wait: bool = True) -> None:
    kind = resource.kind
    if kind == "instance":
        if wait:
            return c.delete_server(resource.id)
        return c.api("delete server", c.compute.delete_server, resource.id, ignore_missing=True)
    if kind == "key_pair":
        return c.api("delete key pair", c.compute.delete_keypair, resource.id, ignore_missing=True)
    if kind == "image":
        return c.api("delete image", c.image.delete_image, resource.id, ignore_missing=True)
    if kind == "router":  # Neutron refuses to delete a router that still has interfaces
        for subnet_id in network.router_subnets(c, resource):
            # positional: the keyword is subnet_id in openstacksdk 3, subnet in 4
            c.api("remove router interface", c.network.remove_interface_from_router, resource.id, subnet_id)
    remove = getattr(c.network, NEUTRON[kind][2])
    c.api(f"delete {kind}", remove, resource.id, ignore_missing=True)


def teardown(c: OpenStackClient) -> list[str]:
    """Every owned resource but the snapshots (they outlive the fleet's clones), servers first."""
    with c.errors(f"teardown of fleet {c.fleet}"):
        doomed = [r for r in list_owned(c) if r.kind != "image"]
        servers = [r for r in doomed if r.kind == "instance"]
        for r in servers:  # all deletions first, then one wait each: servers go in parallel
            delete(c, r, wait=False)
        for r in servers:
            c.delete_server(r)
        for r in doomed:
            if r.kind != "instance":
                delete(c, r)
        c.forget_cached()
        return [f"{r.kind} {r.name or r.id}" for r in doomed]


def leftovers(c: OpenStackClient) -> list[str]:
    """What `fleet down` should have removed and did not (snapshots stay on purpose)."""
    return [f"{r.kind} {r.name or r.id}" for r in list_owned(c) if r.kind != "image"]
