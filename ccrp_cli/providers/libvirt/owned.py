"""What a libvirt fleet owns (what `ccrp gc` sees and `fleet down` removes): its domains (by
metadata), its simulated robots' containers on this host, its port forwards, its volumes and
networks (by name) and its golden volumes; deleting one after checking it is the fleet's."""

from __future__ import annotations

import re

from ...errors import CcrpError
from ..base import LABEL_FLEET, LABEL_ROBOT, LABEL_ROLE, OwnedResource, Role, with_roles
from . import forward, images, network, xmldefs
from .client import LibvirtClient

# A clone's volumes after `ccrp-<fleet>-cri-`: its robot, then what it is (LibvirtClient.clone_volumes).
CLONE_VOLUME = re.compile(r"^(?P<robot>[a-z][a-z0-9]*)(\.qcow2|-seed\.iso|\.console)$")
# What each kind is to the fleet (`ccrp gc`); volumes and port forwards belong to a robot.
ROLES = {"instance": Role.CLONE, "robot_sim": Role.ROBOT_SIDE, "image": Role.IMAGE, "network": Role.BOOTSTRAP}
SHOWN_KINDS = {"instance": "domain", "robot_sim": "container", "port_forward": "port forward"}  # as `fleet down` reports them
ORDER = ("instance", "robot_sim", "port_forward", "volume", "network", "image")


def shown(r: OwnedResource) -> str:
    return f"{SHOWN_KINDS.get(r.kind, r.kind)} {r.name or r.id}"


def sims(c: LibvirtClient) -> list:
    """The fleet's simulated robots and power devices (containers labelled with its name)."""
    host = c.docker_host()
    if host is None:
        return []
    return [s for s in host.engine.containers.list(all=True, ignore_removed=True,
                                                   filters={"label": [f"{LABEL_FLEET}={c.fleet}"]})
            if s.labels.get(LABEL_ROLE) in ("robot-sim", "power-sim")]


def list_owned(c: LibvirtClient) -> list[OwnedResource]:
    """Domains (by metadata), then volumes and networks (by name), in deletion order."""
    with c.errors("list owned resources"):
        found = [OwnedResource(kind="instance", id=d.UUIDString(), name=d.name(), robot=i.labels.get(LABEL_ROBOT))
                 for d, i in c.domains()]
        # Power devices first: they hold their robot's power line volume (docker/robots.py).
        found += [OwnedResource(kind="robot_sim", id=s.id[:12], name=s.name, robot=s.labels.get(LABEL_ROBOT))
                  for s in sorted(sims(c), key=lambda s: s.labels.get(LABEL_ROLE) != "power-sim")]
        pool = c.refreshed(c.pool())
        names = [v.name() for v in pool.listAllVolumes(0) if c.owns_name(v.name())]
        goldens = {n.removesuffix(".qcow2") for n in names if images.GOLDEN.match(n)}
        for name in names:
            stem, _dot, ext = name.rpartition(".")
            if m := images.GOLDEN.match(name):  # a snapshot; its kernel and initramfs go with it
                found.append(OwnedResource(kind="image", id=name, name=name, robot=m["robot"]))
            elif not (ext in ("vmlinuz", "initrd") and stem in goldens):
                m = CLONE_VOLUME.match(name.removeprefix(c.name("cri") + "-"))
                found.append(OwnedResource(kind="volume", id=name, name=name, robot=m["robot"] if m else None))
        found += [OwnedResource(kind="network", id=n.name(), name=n.name())
                  for n in c.conn.listAllNetworks(0) if n.name() in (c.public_net, c.common_net)]
        found += network.forwards(c)
        return with_roles(sorted(found, key=lambda r: ORDER.index(r.kind)), ROLES)


def delete_owned(c: LibvirtClient, resource: OwnedResource) -> None:
    with c.errors(f"delete {resource.kind} {resource.id}"):
        if resource.kind == "instance":
            try:
                dom = c.conn.lookupByUUIDString(resource.id)
            except c.libvirt.libvirtError as exc:
                if c.missing(exc, "VIR_ERR_NO_DOMAIN"):
                    raise CcrpError(f"instance {resource.id} is gone") from None
                raise
            if not c.owns_name(dom.name()) or not c.is_owned(xmldefs.domain_info(dom.XMLDesc(0)).labels):
                raise CcrpError(f"domain {dom.name()} is not fleet {c.fleet!r}'s; not deleting it")
            if dom.isActive():
                dom.destroy()
            dom.undefine()
        elif resource.kind == "robot_sim":
            delete_sim(c, resource.id)
        elif resource.kind == "port_forward":
            if resource.robot is None or resource.id != forward.comment(c.fleet, resource.robot):
                raise CcrpError(f"port forward {resource.id} is not fleet {c.fleet!r}'s; not deleting it")
            if not forward.remove(c.fleet, resource.robot):
                raise CcrpError(f"port forward {resource.id} is gone")
        elif not c.owns_name(resource.id):
            raise CcrpError(f"{resource.kind} {resource.id} is not fleet {c.fleet!r}'s; not deleting it")
        elif resource.kind == "image":
            images.delete_snapshot(c, resource.id) if images.GOLDEN.match(resource.id) else \
                c.delete_vol(c.refreshed(c.pool()), resource.id)
        elif resource.kind == "volume":
            if not c.delete_vol(c.refreshed(c.pool()), resource.id):
                raise CcrpError(f"volume {resource.id} is gone")
        elif resource.kind == "network":
            if resource.id not in (c.public_net, c.common_net):
                raise CcrpError(f"network {resource.id} is not fleet {c.fleet!r}'s; not deleting it")
            network.remove_network(c, resource.id)
        else:
            raise CcrpError(f"unknown resource kind {resource.kind!r}")


def delete_sim(c: LibvirtClient, container_id: str) -> None:
    """A simulated robot or power device of the fleet; its veth goes with its network namespace."""
    found = [s for s in sims(c) if s.id.startswith(container_id)]
    if not found:
        raise CcrpError(f"simulated robot {container_id} is gone or not fleet {c.fleet!r}'s")
    found[0].remove(force=True, v=True)
    if found[0].labels.get(LABEL_ROLE) == "robot-sim":
        network.release_robot_port(c, found[0].labels.get(LABEL_ROBOT, ""))


def teardown(c: LibvirtClient) -> list[str]:
    """Every domain, volume and network of the fleet; golden volumes stay (snapshots outlive
    the fleet's clones, as on the clouds)."""
    with c.errors(f"teardown of fleet {c.fleet}"):
        doomed = [r for r in list_owned(c) if r.kind != "image"]
        for r in doomed:
            if r.kind in ("instance", "robot_sim", "port_forward"):
                delete_owned(c, r)
        pool = c.refreshed(c.pool())
        for r in doomed:
            if r.kind == "volume":
                c.delete_vol(pool, r.id)
            elif r.kind == "network":
                network.remove_network(c, r.id)
        return [shown(r) for r in doomed]


def leftovers(c: LibvirtClient) -> list[str]:
    return [shown(r) for r in list_owned(c) if r.kind != "image"]
