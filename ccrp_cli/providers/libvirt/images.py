"""The fleet's snapshots on libvirt: golden volumes (a qcow2 disk with the kernel and initramfs it
boots, three volumes of the storage pool), built on this machine (Ability.LOCAL_BUILD, goldens.py),
imported, copied from a stopped clone's disk, listed and deleted."""

from __future__ import annotations

import datetime as dt
import re
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

from ...errors import CcrpError
from ..base import SnapshotRecord, owner_labels
from . import xmldefs
from .client import LibvirtClient

GOLDEN = re.compile(r"^ccrp-(?P<fleet>[a-z][a-z0-9]*)-golden-(?:(?P<robot>[a-z][a-z0-9]*)-)?(?P<stamp>\d{14})\.qcow2$")


def stamp() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d%H%M%S")


def golden(c: LibvirtClient, image: str) -> tuple[str, str, str]:
    """The golden volume's path, and its kernel's and initramfs's (volumes beside it)."""
    pool = c.pool()
    stem = image.removesuffix(".qcow2")
    vols = [c.vol(pool, n) for n in (image, f"{stem}.vmlinuz", f"{stem}.initrd")]
    if not image.endswith(".qcow2") or any(v is None for v in vols):
        raise CcrpError(f"golden volume {image} (with its .vmlinuz and .initrd) is not in storage pool {c.settings.pool}",
                        hint="import the fleet's snapshot (docs/libvirt.md)")
    return tuple(v.path() for v in vols)


def has_image(c: LibvirtClient, image: str) -> bool:
    try:
        golden(c, image)
        return True
    except CcrpError:
        return False


def build_snapshot(c: LibvirtClient, repo: str, distro: str, plat, agents: tuple[str, ...], software, digest: str,
                   bare: bool, progress) -> SnapshotRecord:
    """Ability.LOCAL_BUILD: the golden volume made on this machine. The recipe's image is built
    on the local Docker engine as the Docker backend builds its snapshot (the same recipe,
    agents, software and bare variant; no image is downloaded), goldens.build turns it into a qcow2
    with its kernel and initramfs, and those are uploaded to the pool. The intermediate image
    is removed after; the layers under it stay the next build's cache."""
    from ..docker.images import DEFAULT_BASE, build_snapshot_image
    from ..sdk import docker_module
    from . import goldens

    docker = docker_module()
    try:
        client = docker.from_env(timeout=900)
        client.ping()
    except docker.errors.DockerException as exc:
        raise CcrpError(f"the libvirt backend builds its golden volume with a local Docker engine, and none "
                        f"answers ({type(exc).__name__})", hint="start it: bash scripts/docker-engine.sh") from None
    tag = build_snapshot_image(client, repo, c.fleet, distro, DEFAULT_BASE, plat, agents, software, bare,
                               owner_labels(c.fleet, "snapshot") | {"ccrp-software": digest}, progress)
    try:
        with tempfile.TemporaryDirectory(prefix="ccrp-golden-") as tmp:
            made = goldens.build(client, tag, Path(tmp), progress)
            progress(f"uploading the golden volume ({made.qcow2.stat().st_size >> 20} MB) to pool "
                     f"{c.settings.pool}")
            c.pool(create=True)
            return import_golden(c, made.qcow2, made.kernel, made.initrd, made.virtual_size)
    finally:
        try:
            client.images.remove(tag, force=True)
        except docker.errors.APIError:  # in use or gone: `ccrp gc` on Docker finds it
            pass
        client.close()


def import_golden(c: LibvirtClient, qcow2: Path, kernel: Path, initrd: Path, virtual_size: int,
                  robot: str | None = None) -> SnapshotRecord:
    """Upload a golden disk (goldens.py builds it) with its kernel and initramfs as the fleet's
    volumes; a failure leaves none of the three."""
    name = f"{c.name('golden', *([robot] if robot else []), stamp())}.qcow2"
    stem = name.removesuffix(".qcow2")
    with c.errors(f"import of {name}"):
        pool = c.pool()
        done = []
        try:
            for vol, path, fmt, size in ((name, qcow2, "qcow2", virtual_size), (f"{stem}.vmlinuz", kernel, "raw", None),
                                         (f"{stem}.initrd", initrd, "raw", None)):
                c.upload(pool, vol, path, fmt, size)
                done.append(vol)
        except BaseException:
            for vol in done:
                c.delete_vol(pool, vol)
            raise
        return snapshot_record(c.refreshed(pool).storageVolLookupByName(name))


def snapshot_record(vol) -> SnapshotRecord:
    m = GOLDEN.match(vol.name())
    when = dt.datetime.strptime(m["stamp"], "%Y%m%d%H%M%S").isoformat() if m else ""
    return SnapshotRecord(id=vol.name(), name=vol.name(), created=when, source=(m["robot"] if m else None) or "build",
                          size_mb=round(vol.info()[2] / 1e6, 1))


def list_snapshots(c: LibvirtClient) -> list[SnapshotRecord]:
    with c.errors("list snapshots"):
        pool = c.refreshed(c.pool())
        vols = [v for v in pool.listAllVolumes(0) if (m := GOLDEN.match(v.name())) and m["fleet"] == c.fleet]
        return sorted((snapshot_record(v) for v in vols), key=lambda s: s.created)


def delete_snapshot(c: LibvirtClient, snapshot_id: str) -> None:
    m = GOLDEN.match(snapshot_id)
    if not m or m["fleet"] != c.fleet:
        raise CcrpError(f"{snapshot_id} is not a snapshot of fleet {c.fleet!r}", hint="ccrp snapshot list")
    with c.errors(f"delete snapshot {snapshot_id}"):
        pool = c.refreshed(c.pool())
        if not c.delete_vol(pool, snapshot_id):
            raise CcrpError(f"snapshot {snapshot_id} not found", hint="ccrp snapshot list")
        stem = snapshot_id.removesuffix(".qcow2")
        for extra in (f"{stem}.vmlinuz", f"{stem}.initrd"):
            c.delete_vol(pool, extra)


def create_snapshot(c: LibvirtClient, robot: str, name: str) -> SnapshotRecord:
    """The stopped clone's disk flattened into a new golden volume (libvirt copies it through
    its backing chain), with the kernel and initramfs it boots. A running clone is refused:
    QEMU holds its disk's write lock, and the copy (`qemu-img convert`) failed on it even with
    the VM paused (measured)."""
    with c.errors(f"snapshot of {robot}"):
        dom, _info = c.domain(robot)
        if dom is None:
            raise CcrpError(f"robot {robot!r} has no clone", hint=f"ccrp clone create --robot {robot}")
        if dom.isActive():
            raise CcrpError(f"the clone of {robot} is running: a libvirt snapshot copies a stopped clone's disk",
                            hint=f"ccrp clone stop --robot {robot}, then snapshot it")
        pool = c.refreshed(c.pool())
        target = f"{c.name('golden', robot, stamp())}.qcow2"
        stem = target.removesuffix(".qcow2")
        os_ = ET.fromstring(dom.XMLDesc(0)).find("os")
        if os_ is None:  # every domain ccrp defines boots a kernel (xmldefs.domain)
            raise CcrpError(f"the domain of robot {robot!r} names no kernel to copy")
        sources = [(pool.storageVolLookupByName(c.clone_volumes(robot)["disk"]), target, "qcow2")]
        sources += [(c.conn.storageVolLookupByPath(os_.findtext(tag)), f"{stem}.{ext}", "raw")
                    for tag, ext in (("kernel", "vmlinuz"), ("initrd", "initrd"))]
        done = []
        try:
            for src, new, fmt in sources:
                c.api(f"copy volume {new}", pool.createXMLFrom, xmldefs.volume(new, src.info()[1], fmt), src, 0)
                done.append(new)
        except BaseException:
            for new in done:
                c.delete_vol(pool, new)
            raise
        return snapshot_record(pool.storageVolLookupByName(target))
