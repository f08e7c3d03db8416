"""What a Docker fleet owns on this host (what `ccrp gc` sees and `fleet down` removes): the
containers, volumes and networks carrying its labels, its snapshot images and deploy's builds;
deleting one after checking its labels again."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_FLEET, LABEL_ROBOT, LABEL_ROLE, OwnedResource, Role, with_roles
from . import images
from .client import DockerHost


def teardown(c: DockerHost) -> list[str]:
    """Remove every container, volume and network carrying the fleet's labels."""
    removed = []
    found = c.engine.containers.list(all=True, ignore_removed=True, filters={"label": [f"{LABEL_FLEET}={c.fleet}"]})
    # A simulated power device first: it holds its robot's power-line volume, which goes with the robot.
    for ct in sorted(found, key=lambda ct: ct.labels.get(LABEL_ROLE) != "power-sim"):
        ct.remove(force=True, v=True)
        removed.append(f"container {ct.name}")
    for v in c.engine.volumes.list(filters={"label": [f"{LABEL_FLEET}={c.fleet}"]}):
        v.remove(force=True)
        removed.append(f"volume {v.name}")
    for n in c.engine.networks.list(filters={"label": [f"{LABEL_FLEET}={c.fleet}"]}):
        n.remove()
        removed.append(f"network {n.name}")
    return removed


# What each kind is to the fleet (`ccrp gc`); volumes belong to a robot.
ROLES = {"container": Role.CLONE, "robot_sim": Role.ROBOT_SIDE, "image": Role.IMAGE, "network": Role.BOOTSTRAP}


def list_owned(c: DockerHost) -> list[OwnedResource]:
    label = {"label": [f"{LABEL_FLEET}={c.fleet}"]}
    owned = [
        OwnedResource(kind="container" if ct.labels.get(LABEL_ROLE) == "clone" else "robot_sim", id=ct.id[:12],
                      name=ct.name, robot=ct.labels.get(LABEL_ROBOT))
        for ct in c.engine.containers.list(all=True, ignore_removed=True, filters=label)
    ]
    owned += [OwnedResource(kind="volume", id=v.name, name=v.name, robot=(v.attrs.get("Labels") or {}).get(LABEL_ROBOT))
              for v in c.engine.volumes.list(filters=label)]
    owned += [OwnedResource(kind="network", id=n.name, name=n.name) for n in c.engine.networks.list(filters=label)]
    owned += [OwnedResource(kind="image", id=s.id, name=s.name, robot=None if s.source == "build" else s.source)
              for s in images.list_snapshots(c)]
    # `ccrp deploy`'s build of the workspace (deploy.py): cache only, no state records it.
    owned += [OwnedResource(kind="image", id=i.id.removeprefix("sha256:")[:12], name=(i.tags or ["<untagged>"])[0])
              for i in c.engine.images.list(filters=c.filters("deploy"))]
    return with_roles(owned, ROLES)


def delete_owned(c: DockerHost, resource: OwnedResource) -> None:
    getter = {"container": c.engine.containers, "robot_sim": c.engine.containers, "volume": c.engine.volumes,
              "network": c.engine.networks, "image": c.engine.images}[resource.kind]
    try:
        obj = getter.get(resource.id)
    except c.NotFound:
        raise CcrpError(f"{resource.kind} {resource.id} is gone") from None
    labels = obj.labels if resource.kind in ("container", "robot_sim", "image") else obj.attrs.get("Labels") or {}
    if labels.get(LABEL_FLEET) != c.fleet:  # checked again: never remove what is not ours
        raise CcrpError(f"{resource.kind} {resource.id} is not owned by fleet {c.fleet!r}")
    if resource.kind == "image":
        c.engine.images.remove(obj.id, force=True)
    elif resource.kind == "network":
        obj.remove()
    else:
        obj.remove(force=True, **({"v": True} if resource.kind != "volume" else {}))


def leftovers(c: DockerHost) -> list[str]:
    label = {"label": [f"{LABEL_FLEET}={c.fleet}"]}
    return (
        [f"container {ct.name}" for ct in c.engine.containers.list(all=True, ignore_removed=True, filters=label)]
        + [f"volume {v.name}" for v in c.engine.volumes.list(filters=label)]
        + [f"network {n.name}" for n in c.engine.networks.list(filters=label)]
    )
