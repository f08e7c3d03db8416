"""The golden volume of a libvirt fleet, made from the fleet's Docker snapshot image (the recipe
built from Debian packages by `ccrp snapshot build`): no image is downloaded.

One layer over the snapshot adds what a VM needs and a container does not (a kernel and its
initramfs, udev, sshd, sudo, systemd-networkd, cloud-init's network and SSH modules); the layer's
file system is exported, written into an ext4 file system image (`mkfs.ext4 -d`: no loop mount,
no privileges beyond reading the tree) and converted to qcow2. The kernel and initramfs are kept
beside it: clones boot them directly (no bootloader), with the whole disk as their root.

Tools on the operator's machine: the Docker engine, tar, mkfs.ext4 (e2fsprogs), qemu-img
(qemu-utils). Everything is run with argument lists, never through a shell."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from ...errors import CcrpError
from .seed import NIC_NAMES

# What a VM needs beyond the container snapshot: the cloud kernel (virtio drivers, a small module
# set) with initramfs-tools, udev (modules for the devices it finds), sshd (the transport), sudo
# (the login user's), e2fsprogs (fsck of the root at boot), systemd-resolved (the resolver: it takes
# the DNS server systemd-networkd got by DHCP, the NAT network's dnsmasq; networkd alone writes no
# resolv.conf, and a container's comes from Docker), QEMU's guest agent (the clock, below).
VM_PACKAGES = ["linux-image-cloud-amd64", "udev", "openssh-server", "sudo", "e2fsprogs", "systemd-resolved",
               "qemu-guest-agent"]

# A VM's clock starts from the emulated RTC, which holds whole seconds: without KVM's paravirtual
# clock a clone started up to a second behind the host (a robot's or a peer clone's stamps then
# looked up to a second old or in the future). The provider sets the clone's clock from the host's
# through the guest agent once it boots (provider.py sync_clock). The agent answers only the RPCs
# that needs; every other one (guest-exec, file access, SSH keys, passwords...) is blocked, the
# list read from the installed agent itself so that none added by a newer version slips through.
GUEST_AGENT_RPCS = ("guest-sync-delimited", "guest-sync", "guest-ping", "guest-info", "guest-get-time",
                    "guest-set-time")

# No IPv6 router advertisements listened for on the clone's NICs (the fleet's networks are IPv4
# only, xmldefs.py): while systemd-networkd solicits a router, a link without DHCP (the common one)
# stays "configuring" until its NDisc timeout, and systemd-networkd-wait-online, which cloud-init's
# network stage waits for, held the first boot 12 s (IPv6 link-local at 42.0 s of uptime,
# wait-online done at 54.1 s). cloud-init 22.4 renders `accept-ra` only for DHCPv6 links, so the
# setting is a drop-in beside the .network file it writes for each NIC (named in seed.py).
NO_RA_DROPIN = "[Network]\nIPv6AcceptRA=no\n"
NO_RA_DROPINS = [f"/etc/systemd/network/10-cloud-init-{name}.network.d/90-ccrp-no-ra.conf" for name in NIC_NAMES]

# resolved answers on 127.0.0.53 only: no LLMNR or multicast DNS responder (on by default, UDP/TCP
# 5355 and UDP 5353 on every link) on the clone's networks, where nothing asks for one.
RESOLVED_CONF = "[Resolve]\nLLMNR=no\nMulticastDNS=no\n"

# cloud-init in the VM: the container snapshot's module lists (templates/docker/Dockerfile.j2) and,
# as on the clouds, `ssh` (host keys made at first boot; Ed25519 and ECDSA only: an RSA key costs
# seconds in an emulated guest) and `keys-to-console` (their fingerprints on the serial console, which
# ccrp pins them from). The network is cloud-init's again (the seed's network-config), rendered for
# systemd-networkd.
# keys-to-console runs right after `ssh`, in the network stage, not at the end of the final stage as
# on the clouds: ccrp logs in as soon as the keys are on the console, so its login and its wait for
# cloud-init's result overlap the config and final stages instead of following them (the keys and
# their pinning are the same).
CLOUD_CFG = """\
datasource_list: [ NoCloud, ConfigDrive, None ]
system_info:
  network:
    renderers: [ networkd ]
ssh_genkeytypes: [ ed25519, ecdsa ]
ssh_deletekeys: true
ssh_pwauth: false
cloud_init_modules: [ bootcmd, write-files, set_hostname, update_hostname, update_etc_hosts, users-groups, ssh, keys-to-console ]
cloud_config_modules: [ locale, apt-configure, runcmd ]
cloud_final_modules: [ package-update-upgrade-install, write-files-deferred, scripts-per-once, scripts-per-boot, scripts-per-instance, scripts-user, ssh-authkey-fingerprints, final-message ]
"""

# e2scrub_reap (e2fsprogs) looks for stale e2scrub snapshots of LVM volumes at every boot; a clone's
# disk is one ext4 file system, and on a 1-vCPU TCG guest the unit took 32 s of its boot (measured).

# ROS 1's roscore gives the master it starts 10 s to answer (roslaunch's _TIMEOUT_MASTER_START), then
# gives up; systemd starts it again. Under TCG on a busy host rosmaster's Python imports alone took
# longer: one clone's master came up at its third try, another's not within 9 minutes (measured), so
# a VM's roscore waits up to 180 s.
DOCKERFILE = """\
# A ccrp snapshot made a VM's root file system (ccrp_cli/providers/libvirt/goldens.py).
FROM {base}
COPY initramfs-modules /usr/share/initramfs-tools/modules.d/ccrp-config-drive
RUN apt-get update \\
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends {packages} \\
 && rm -rf /var/lib/apt/lists/*
COPY 90-ccrp.cfg /etc/cloud/cloud.cfg.d/90-ccrp.cfg
COPY ds-identify.cfg /etc/cloud/ds-identify.cfg
COPY fstab /etc/fstab
COPY resolved.conf /etc/systemd/resolved.conf.d/90-ccrp.conf
{no_ra}RUN mkdir -p /etc/qemu && blocked=$(qemu-ga --block-rpcs=help | grep -vxE '{agent_rpcs}' | paste -sd, -) \\
 && [ -n "$blocked" ] && printf '[general]\\nblock-rpcs=%s\\n' "$blocked" > /etc/qemu/qemu-ga.conf
RUN f=/usr/lib/python3/dist-packages/roslaunch/launch.py; [ ! -f "$f" ] \\
 || sed -i 's/^_TIMEOUT_MASTER_START = 10.0 /_TIMEOUT_MASTER_START = 180.0 /' "$f" && ! grep -q '^_TIMEOUT_MASTER_START = 10.0 ' "$f"
RUN rm -f /etc/ssh/ssh_host_* \\
 && systemctl unmask cloud-init-local.service systemd-logind.service \\
 && systemctl enable systemd-networkd.service systemd-resolved.service ssh.service cloud-init-local.service \\
      cloud-init.service cloud-config.service cloud-final.service \\
 && systemctl mask e2scrub_reap.service \\
 && rm -rf /var/lib/cloud/instance /var/lib/cloud/instances \\
 && : > /etc/machine-id
"""
# The same golden boots on OpenStack (scripts/openstack.sh uploads one to Glance): Nova hands
# cloud-init its data on a config drive, an ISO on an IDE CD-ROM of QEMU's `pc` machine. cloud-init's
# ds-identify (a systemd generator, at the very start of boot) decides whether cloud-init runs at all;
# on Nova it disabled it (no host keys, no user-data: the console showed no cloud-init line), first
# with the CD-ROM's drivers only on the root file system, then still with them in the initramfs (sr0
# found 1.4 s before the root was mounted). With `policy: enabled` cloud-init always runs and tries
# the datasource list itself, NoCloud first (libvirt's seed, as before), then the config drive, which
# it finds by its label once udev has settled. The drivers stay in the initramfs: the drive is there
# from the start.
INITRAMFS_MODULES = "ata_piix\nsr_mod\n"
DS_IDENTIFY_CFG = "policy: enabled\n"
FSTAB = "/dev/vda / ext4 defaults,errors=remount-ro 0 1\n"
DISK_BYTES = 8 << 30  # the root file system's size: the recipe takes about 1.5 GB of it


def dockerfile(base: str) -> str:
    return DOCKERFILE.format(base=base, packages=" ".join(VM_PACKAGES),
                             no_ra="".join(f"COPY no-ra.conf {path}\n" for path in NO_RA_DROPINS),
                             agent_rpcs="|".join(GUEST_AGENT_RPCS))


@dataclass
class Golden:
    qcow2: Path
    kernel: Path
    initrd: Path
    virtual_size: int
    seconds: dict[str, float] = field(default_factory=dict)  # step -> wall time

    @property
    def directory(self) -> Path:
        return self.qcow2.parent


def _tool(name: str, package: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise CcrpError(f"{name} is not installed (it writes the golden volume)", hint=f"apt-get install {package}")
    return path


def _run(argv: list[str], what: str) -> None:
    proc = subprocess.run(argv, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise CcrpError(f"{what} failed: {(proc.stderr or proc.stdout).strip()[-300:]}")


def build(client, snapshot_image: str, out_dir: Path, progress=lambda msg: None, disk_bytes: int = DISK_BYTES,
          keep_layer: bool = False) -> Golden:
    """The golden qcow2, kernel and initramfs in `out_dir`, from `snapshot_image` (a Docker image
    `ccrp snapshot build` made). Timings of each step in Golden.seconds."""
    from ..docker.images import build_clone_image

    tar, mkfs, qemu_img = _tool("tar", "tar"), _tool("mkfs.ext4", "e2fsprogs"), _tool("qemu-img", "qemu-utils")
    out_dir.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    tag = f"{snapshot_image.rsplit(':', 1)[0]}:vm-{int(time.time())}"
    t0 = time.monotonic()
    progress(f"adding a kernel, sshd and networkd to {snapshot_image} ({tag})")
    build_clone_image(client, tag, dockerfile(snapshot_image), {"ccrp-libvirt-golden": snapshot_image}, progress,
                      files={"90-ccrp.cfg": CLOUD_CFG.encode(), "fstab": FSTAB.encode(),
                             "resolved.conf": RESOLVED_CONF.encode(), "no-ra.conf": NO_RA_DROPIN.encode(),
                             "initramfs-modules": INITRAMFS_MODULES.encode(), "ds-identify.cfg": DS_IDENTIFY_CFG.encode()},
                      what="golden volume layer")
    seconds["vm layer (docker build)"] = time.monotonic() - t0
    container = None
    try:
        with tempfile.TemporaryDirectory(prefix="ccrp-golden-", dir=out_dir) as tmp:
            root = Path(tmp) / "root"
            root.mkdir()
            t0 = time.monotonic()
            container = client.containers.create(tag, command=["/bin/true"])
            _export(container, tar, root)
            seconds["export + untar"] = time.monotonic() - t0
            # Docker mounts its own /etc/resolv.conf over the image's in every build step, so the
            # link to resolved's stub (what Debian's systemd-resolved package makes) is made here.
            resolv = tree_path(root, "etc") / "resolv.conf"  # not through a link out of the tree
            resolv.unlink(missing_ok=True)
            resolv.symlink_to("../run/systemd/resolve/stub-resolv.conf")
            kernel, initrd = _boot_files(root, out_dir)
            t0 = time.monotonic()
            raw = Path(tmp) / "root.img"
            with open(raw, "wb") as fh:
                fh.truncate(disk_bytes)  # sparse
            progress(f"writing the root file system ({disk_bytes >> 30} GiB ext4, sparse)")
            _run([mkfs, "-F", "-q", "-L", "ccrp-root", "-d", str(root), str(raw)], "mkfs.ext4 -d")
            seconds["mkfs.ext4 -d"] = time.monotonic() - t0
            t0 = time.monotonic()
            qcow2 = out_dir / "golden.qcow2"
            _run([qemu_img, "convert", "-f", "raw", "-O", "qcow2", str(raw), str(qcow2)], "qemu-img convert")
            seconds["qemu-img convert"] = time.monotonic() - t0
    finally:
        if container is not None:
            container.remove(force=True)
        if not keep_layer:
            client.images.remove(tag, force=True)
    return Golden(qcow2=qcow2, kernel=kernel, initrd=initrd, virtual_size=disk_bytes, seconds=seconds)


def _export(container, tar: str, root: Path) -> None:
    """`docker export` streamed into tar (owners, modes, xattrs such as file capabilities kept)."""
    proc = subprocess.Popen([tar, "--numeric-owner", "--xattrs", "--xattrs-include=*", "-xpf", "-", "-C", str(root)],
                            stdin=subprocess.PIPE, stderr=subprocess.PIPE)
    stdin, stderr = proc.stdin, proc.stderr
    assert stdin is not None and stderr is not None  # both piped above
    err: list[bytes] = []
    reader = threading.Thread(target=lambda: err.append(stderr.read()), daemon=True)
    reader.start()
    try:
        for chunk in container.export():
            stdin.write(chunk)
    except BrokenPipeError:
        pass
    finally:
        stdin.close()
        rc = proc.wait()
        reader.join()
    if rc != 0:
        raise CcrpError(f"unpacking the snapshot's files failed: {b''.join(err).decode(errors='replace').strip()[-300:]}")


# Links followed on one path at most (Linux's own limit, past which it says ELOOP).
MAX_LINKS = 40


def tree_path(root: Path, rel: str) -> Path:
    """Where `rel` is in the tree at `root` as the tree's own system would see it: each link on the
    way followed from the tree's root (an absolute link is a path of the tree, `..` stops at its
    root), so no link leads out of it. The tree is the build's, which its packages (the workspace's
    too) wrote, and ccrp reads it as root: a boot/vmlinuz-* pointing at the fleet's CA key would
    have become a pool volume, maybe on another host. The path returned has no link left in it."""
    todo = [part for part in PurePosixPath(rel).parts if part != "/"]
    done: list[str] = []
    links = 0
    while todo:
        part = todo.pop(0)
        if part == "..":
            if done:
                done.pop()
            continue
        here = root.joinpath(*done, part)
        if not here.is_symlink():
            done.append(part)
            continue
        links += 1
        if links > MAX_LINKS:
            raise CcrpError(f"the golden tree's /{rel} goes through more than {MAX_LINKS} links")
        target = os.readlink(here)
        if target.startswith("/"):
            done = []
        todo = [p for p in PurePosixPath(target).parts if p != "/"] + todo
    return root.joinpath(*done)


def _boot_files(root: Path, out_dir: Path) -> tuple[Path, Path]:
    """The kernel and initramfs of the tree (one each: the layer installs one kernel), copied out:
    regular files of the tree, links followed inside it only (tree_path)."""
    boot = tree_path(root, "boot")
    kernels = sorted(boot.glob("vmlinuz-*"))
    initrds = sorted(boot.glob("initrd.img-*"))
    if len(kernels) != 1 or len(initrds) != 1:
        raise CcrpError(f"the golden tree has {len(kernels)} kernels and {len(initrds)} initramfs images, not one each")
    out = []
    for found, name in ((kernels[0], "vmlinuz"), (initrds[0], "initrd.img")):
        rel = found.relative_to(root).as_posix()
        src = tree_path(root, rel)
        try:
            regular = stat.S_ISREG(os.lstat(src).st_mode)
        except FileNotFoundError:
            regular = False
        if not regular:  # a link to nothing in the tree, a directory, a device node or a FIFO
            raise CcrpError(f"the golden tree's /{rel} is not a file of the tree (it leads to /{src.relative_to(root).as_posix()})",
                            hint="a package of the build replaced the kernel: check the fleet's software")
        dest = out_dir / name
        shutil.copyfile(src, dest, follow_symlinks=False)
        os.chmod(dest, 0o644)
        out.append(dest)
    return out[0], out[1]
