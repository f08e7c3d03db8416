"""The tiny VM of the contract harnesses that boot real VMs (libvirt, the real OpenStack): the
Debian cloud kernel and its initramfs with, as the root file system, a static busybox whose init
loads the ACPI button driver and runs acpid, which powers the VM off at the power button (what
`clone stop` presses, and Nova's graceful stop; a clone's systemd does the same). Built once per
machine from Debian's packages (the Docker image ccrp-test/vm-tiny), once per process as files."""

from __future__ import annotations

import atexit
import io
import shutil
import subprocess
import tarfile
import tempfile
from pathlib import Path

BASE = "ccrp/base:bookworm"
TINY = "ccrp-test/vm-tiny:1"
TINY_DOCKERFILE = f"""FROM {BASE}
RUN apt-get update \\
 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends linux-image-cloud-amd64 busybox-static \\
 && rm -rf /var/lib/apt/lists/*
"""
# PID 1 of the tiny VM. acpid runs ./PWRF/00000080 (under /etc/acpi) when the power button is pressed.
INIT = """#!/bin/busybox sh
/bin/busybox mount -t proc proc /proc
/bin/busybox mount -t sysfs sys /sys
/bin/busybox mount -t devtmpfs dev /dev
/bin/busybox insmod /lib/evdev.ko
/bin/busybox insmod /lib/button.ko
/bin/busybox acpid -d -c /etc/acpi &
echo "ccrp contract VM up"
while :; do /bin/busybox sleep 3600; done
"""
POWER_BUTTON = "#!/bin/busybox sh\n/bin/busybox poweroff -f\n"
DISK_BYTES = 16 << 20
# The kernel command line the root file system boots with (libvirt's xmldefs.DomainSpec.cmdline).
from ccrp_cli.providers.libvirt.xmldefs import KERNEL_CMDLINE as CMDLINE  # noqa: E402 - the golden's

_TINY: dict[str, Path] = {}


def tiny_files(client) -> dict[str, Path]:
    """The tiny VM's kernel, initramfs and root file system (qcow2), made once per process:
    {"kernel", "initrd", "qcow2"}. `client` is a docker client; ccrp's base image must exist
    (tests.e2e.fleet.ensure_base)."""
    if _TINY:
        return _TINY
    try:
        client.images.get(TINY)
    except Exception:  # noqa: BLE001 - NotFound: built once per machine
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w") as tar:
            info = tarfile.TarInfo("Dockerfile")
            info.size = len(TINY_DOCKERFILE)
            tar.addfile(info, io.BytesIO(TINY_DOCKERFILE.encode()))
        buf.seek(0)
        client.images.build(fileobj=buf, custom_context=True, tag=TINY, rm=True)
    out = Path(tempfile.mkdtemp(prefix="ccrp-contract-vm-"))
    atexit.register(shutil.rmtree, out, True)
    container = client.containers.create(TINY, command=["/bin/true"])
    try:
        for src in ("/boot", "/bin/busybox", "/lib/modules"):
            stream, _ = container.get_archive(src)
            with tarfile.open(fileobj=io.BytesIO(b"".join(stream))) as tar:
                tar.extractall(out / "x", filter="tar")
    finally:
        container.remove(force=True)
    root = out / "root"
    for d in ("bin", "sbin", "lib", "proc", "sys", "dev", "run", "var/log", "etc/acpi/PWRF"):
        (root / d).mkdir(parents=True, exist_ok=True)
    shutil.copy(out / "x" / "busybox", root / "bin" / "busybox")
    for module in ("input/evdev.ko", "acpi/button.ko"):  # modules of the cloud kernel: the power button's events
        shutil.copy(next((out / "x" / "modules").glob(f"*/kernel/drivers/{module}")), root / "lib")
    for path, text in (("sbin/init", INIT), ("etc/acpi/PWRF/00000080", POWER_BUTTON)):
        (root / path).write_text(text)
        (root / path).chmod(0o755)
    raw = out / "root.img"
    with open(raw, "wb") as fh:
        fh.truncate(DISK_BYTES)
    subprocess.run(["mkfs.ext4", "-F", "-q", "-d", str(root), str(raw)], check=True, capture_output=True)
    subprocess.run(["qemu-img", "convert", "-f", "raw", "-O", "qcow2", str(raw), str(out / "golden.qcow2")],
                   check=True, capture_output=True)
    _TINY.update(qcow2=out / "golden.qcow2", kernel=next((out / "x" / "boot").glob("vmlinuz-*")),
                 initrd=next((out / "x" / "boot").glob("initrd.img-*")))
    return _TINY
