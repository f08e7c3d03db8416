"""The base image of the single-node OpenStack of scripts/openstack.sh: Debian 12 made from Debian's
packages, as ccrp's libvirt backend makes its golden volume, uploaded to Glance under the name
`ccrp snapshot bake` looks for by default (`debian-12-genericcloud-amd64`, Debian's own generic cloud
image there is no downloading here).

What it holds is what Debian's generic cloud image holds for ccrp's purpose and no ROS: systemd,
cloud-init, sshd, sudo, the cloud kernel. `ccrp snapshot bake` installs the fleet's recipe on it on the
cloud, as it does on any OpenStack. Nova's libvirt driver boots the kernel and initramfs directly
(Glance `aki`/`ari` images named by the root image's `kernel_id`/`ramdisk_id`): the golden has no
bootloader, the whole disk is its root.

One addition this host needs and a real cloud image does not: the CAs this machine trusts for its
egress (/usr/local/share/ca-certificates), since the cloud's servers reach Debian's mirrors and PyPI
through the same network as the host (a bake's builder runs apt and pip).

Idempotent: an image of that name whose `ccrp_build` property matches the build's inputs is kept.
Run by scripts/openstack.sh: `.venv/bin/python scripts/openstack_image.py [--cloud ccrp-aio-admin]`."""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

NAME = "debian-12-genericcloud-amd64"
BASE = "ccrp/base-bare:bookworm"
# What Debian's generic cloud image has beyond ccrp's bare base (systemd, cloud-init, locales) and
# the golden's VM layer (kernel, udev, sshd, sudo, networkd, resolved): hostnamectl needs D-Bus.
PACKAGES = ["dbus", "iproute2", "netbase", "procps", "less", "gnupg", "python3"]
CA_DIR = Path("/usr/local/share/ca-certificates")


def layer() -> str:
    return (f"FROM {BASE}\n"
            "COPY extra-ca/ /usr/local/share/ca-certificates/\n"
            "RUN apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "
            f"{' '.join(PACKAGES)} && rm -rf /var/lib/apt/lists/* && update-ca-certificates >/dev/null\n")


def main() -> int:
    import docker
    import openstack

    from ccrp_cli.errors import CcrpError
    from ccrp_cli.providers.docker.images import BARE_PACKAGES, BASE_PACKAGES, build_base_image, build_clone_image
    from ccrp_cli.providers.libvirt import goldens, xmldefs

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cloud", default="ccrp-aio-admin", help="clouds.yaml entry that may upload public images")
    ap.add_argument("--force", action="store_true", help="build and upload even when the image is current")
    args = ap.parse_args()
    say = lambda msg: print(f"ccrp openstack image: {msg}", file=sys.stderr, flush=True)  # noqa: E731
    t0 = time.monotonic()
    cas = {p.name: p.read_bytes() for p in sorted(CA_DIR.glob("*.crt"))}
    # The build's inputs: a change to any of them (the golden's layer, the packages, the CAs) makes a new image.
    digest = hashlib.sha256("\0".join([layer(), goldens.dockerfile(BASE), goldens.CLOUD_CFG, goldens.INITRAMFS_MODULES, goldens.DS_IDENTIFY_CFG,
                                       *(f"{k}={v.hex()}" for k, v in cas.items())]).encode()).hexdigest()[:16]
    conn = openstack.connect(cloud=args.cloud)
    current = [i for i in conn.image.images(name=NAME) if i.status == "active"]
    if not args.force and any((i.properties or {}).get("ccrp_build") == digest for i in current):
        say(f"{NAME} is current (build {digest})")
        return 0
    client = docker.from_env(timeout=600)
    try:
        try:
            client.images.get(BASE)
        except docker.errors.ImageNotFound:
            build_base_image(client, BASE, BASE_PACKAGES + BARE_PACKAGES, say)
        tag = "ccrp/openstack-base:bookworm"
        files = {f"extra-ca/{k}": v for k, v in cas.items()} or {"extra-ca/.keep": b""}
        build_clone_image(client, tag, layer(), {"ccrp-openstack-base": digest}, say, files=files,
                          what="base image layer")
        with tempfile.TemporaryDirectory(prefix="ccrp-os-image-", dir="/var/tmp") as tmp:
            golden = goldens.build(client, tag, Path(tmp), say)
            say(f"built in {time.monotonic() - t0:.0f} s; uploading to Glance ({args.cloud})")
            kernel = conn.image.create_image(name=f"{NAME}-vmlinuz", disk_format="aki", container_format="aki",
                                             visibility="public", filename=str(golden.kernel), ccrp_build=digest)
            initrd = conn.image.create_image(name=f"{NAME}-initrd", disk_format="ari", container_format="ari",
                                             visibility="public", filename=str(golden.initrd), ccrp_build=digest)
            root = conn.image.create_image(name=NAME, disk_format="qcow2", filename=str(golden.qcow2),
                                           kernel_id=kernel.id, ramdisk_id=initrd.id, os_command_line=xmldefs.KERNEL_CMDLINE,
                                           os_distro="debian", os_version="12", ccrp_build=digest, visibility="public",
                                           container_format="bare")
        # The previous build's root image goes once the new one is active; its kernel and initramfs only
        # when no image names them any more: a snapshot of a server booted from it (every clone image
        # `snapshot bake` made) carries its kernel_id and ramdisk_id and boots only while they exist.
        # Parts of an upload interrupted before its root image go the same way.
        for old in current:
            conn.image.delete_image(old, ignore_missing=True)
        # openstacksdk gives kernel_id and ramdisk_id as the Image's own fields, not in `properties`
        # (which held neither: every upload deleted its own kernel and initramfs, and Nova then
        # refused the image: "Can not find requested image").
        named = {getattr(i, k, None) or (i.properties or {}).get(k) for i in conn.image.images() for k in ("kernel_id", "ramdisk_id")}
        for part in [*conn.image.images(name=f"{NAME}-vmlinuz"), *conn.image.images(name=f"{NAME}-initrd")]:
            if part.id not in named:
                conn.image.delete_image(part, ignore_missing=True)
    except CcrpError as exc:
        say(f"FAILED: {exc}")
        return 1
    finally:
        client.close()
    say(f"{NAME} ({root.id}, build {digest}) uploaded in {time.monotonic() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
