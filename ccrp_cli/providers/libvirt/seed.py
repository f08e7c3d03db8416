"""A clone's NoCloud seed: an ISO 9660 volume labelled `cidata` with the user-data ccrp rendered for
it (exactly what the clouds get), its meta-data and a network-config naming each interface by MAC."""

from __future__ import annotations

import ipaddress
import shutil
import subprocess
import tempfile
from pathlib import Path

import yaml

from ...errors import CcrpError

# Which tool makes the ISO, first found: genisoimage (cloud-image-utils' cloud-localds uses it) or
# xorriso's mkisofs emulation; the same arguments for both.
ISO_TOOLS = (("genisoimage",), ("xorriso", "-as", "mkisofs"))


def meta_data(instance_id: str, hostname: str) -> str:
    return yaml.safe_dump({"instance-id": instance_id, "local-hostname": hostname}, sort_keys=False)


# The clone's NICs, named by cloud-init (set-name, matched by MAC) so that the golden volume's
# networkd drop-ins (goldens.py NO_RA_DROPINS) apply to the files cloud-init writes for them.
NIC_NAMES = ("public", "common")


def network_config(public_mac: str, common_mac: str, common_ip: str, common_cidr: ipaddress.IPv4Network) -> str:
    """cloud-init's network config v2: DHCP on the public (NAT) side, the clone's static address on
    the common network, no gateway there (the default route is the public side's)."""
    public, common = NIC_NAMES
    return yaml.safe_dump({"version": 2, "ethernets": {
        public: {"match": {"macaddress": public_mac}, "set-name": public, "dhcp4": True},
        common: {"match": {"macaddress": common_mac}, "set-name": common, "dhcp4": False,
                 "addresses": [f"{common_ip}/{common_cidr.prefixlen}"]},
    }}, sort_keys=False)


def iso_tool() -> tuple[str, ...]:
    for argv in ISO_TOOLS:
        if shutil.which(argv[0]):
            return argv
    raise CcrpError("neither genisoimage nor xorriso is installed to write the clone's NoCloud seed",
                    hint="apt-get install genisoimage (scripts/libvirt.sh installs it)")


def make_iso(files: dict[str, str]) -> bytes:
    """An ISO 9660 image (Joliet and Rock Ridge names) labelled cidata holding `files`."""
    tool = iso_tool()
    with tempfile.TemporaryDirectory(prefix="ccrp-seed-") as tmp:
        src = Path(tmp) / "cidata"
        src.mkdir(mode=0o700)
        for name, content in files.items():
            (src / name).write_text(content)
        out = Path(tmp) / "seed.iso"
        proc = subprocess.run([*tool, "-quiet", "-output", str(out), "-volid", "cidata", "-joliet", "-rock",
                               *(str(src / name) for name in files)], capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            raise CcrpError(f"{tool[0]} could not write the NoCloud seed: {proc.stderr.strip()[-200:]}")
        return out.read_bytes()


def seed_iso(user_data: str, instance_id: str, hostname: str, network: str) -> bytes:
    return make_iso({"user-data": user_data, "meta-data": meta_data(instance_id, hostname), "network-config": network})
