"""`provider:` of an inventory for the libvirt backend."""

from __future__ import annotations

import ipaddress
import re
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, model_validator

from ...models.strict import ProviderSettings
from ...errors import shown

# A libvirt connection URI as `virsh -c` takes it: driver[+transport]://[user@][host][:port]/path[?query],
# one token (no space, quote or shell character): qemu:///system, qemu+ssh://ops@lab1/system...
_URI_RE = re.compile(r"[a-z][a-z0-9]*(\+[a-z0-9]+)?://([A-Za-z0-9._-]+@)?[A-Za-z0-9.:\[\]_-]*/[A-Za-z0-9._/-]*"
                     r"(\?[A-Za-z0-9._=&/-]*)?", re.ASCII)
# A storage pool's name and directory on the libvirt host: one token each.
_POOL_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", re.ASCII)
_DIR_RE = re.compile(r"/[A-Za-z0-9._/-]{1,200}", re.ASCII)


def _uri(text: str) -> str:
    if not _URI_RE.fullmatch(text) or len(text) > 255:
        raise ValueError(f"{shown(text)} is not a libvirt URI (qemu:///system, qemu+ssh://user@host/system)")
    return text


def _pool(text: str) -> str:
    if not _POOL_RE.fullmatch(text):
        raise ValueError(f"{shown(text)} is not a storage pool name (letters, digits, . _ -)")
    return text


def _dir(text: str) -> str:
    if not _DIR_RE.fullmatch(text) or "/../" in f"{text}/" or "//" in text:
        raise ValueError(f"{shown(text)} is not an absolute directory path")
    return text


class LibvirtSettings(ProviderSettings):
    kind: Literal["libvirt"]
    uri: Annotated[str, AfterValidator(_uri)] = "qemu:///system"
    # kvm: hardware virtualisation; tcg: QEMU's emulation (slow, works anywhere); auto: kvm when a
    # probe VM really boots with it, tcg otherwise (a /dev/kvm that opens is not proof: docs/libvirt.md).
    accel: Literal["auto", "kvm", "tcg"] = "auto"
    memory_mb: Annotated[int, Field(strict=True, ge=512, le=262_144)] = 2048
    vcpus: Annotated[int, Field(strict=True, ge=1, le=64)] = 2
    # Quotas before growth (provider.quotas): the host's CPUs times this are the vCPUs its running
    # domains may have in all. 4.0 is OpenStack Nova's initial_cpu_allocation_ratio: vCPUs are
    # threads of QEMU that share cores (slower, not refused); 1.0 keeps one core per vCPU.
    vcpu_overcommit: Annotated[float, Field(strict=True, ge=1.0, le=64.0)] = 4.0
    # What one clone's qcow2 overlay is expected to take of the storage pool, held before a clone is
    # created (and, for a clone's overlay already there, what it has not taken yet). An overlay holds
    # only the clone's writes: 20-25 MB after its first boot here (docs/libvirt.md); the rest is room
    # for journald (by default up to 10% of the 8 GiB root file system: 819 MiB) and ROS logs. The
    # worst case is the golden volume's virtual size (8 GiB): an overlay can grow to it.
    overlay_mb: Annotated[int, Field(strict=True, ge=64, le=1_048_576)] = 1024
    # The fleet's NAT network (plays the clouds' public network): the host is its first address,
    # clones get theirs from its DHCP range.
    public_cidr: ipaddress.IPv4Network = ipaddress.IPv4Network("192.168.150.0/24")
    # Where SSH to the clones may come from (their firewall, templates/clone/firewall.rules.j2): by
    # default the libvirt host's own address on the NAT network, the one way in from outside it.
    operator_cidr: ipaddress.IPv4Network | None = None
    # The storage pool (a directory on the libvirt host) holding golden volumes, overlays, seeds
    # and consoles; created by `fleet up` when missing, shared by fleets, never removed by ccrp.
    pool: Annotated[str, AfterValidator(_pool)] = "ccrp"
    pool_dir: Annotated[str, AfterValidator(_dir)] = "/var/lib/libvirt/images/ccrp"

    def networks(self) -> dict[str, ipaddress.IPv4Network]:
        return {"provider.public_cidr": self.public_cidr}

    def operator_network(self) -> ipaddress.IPv4Network | None:
        return self.operator_cidr

    @model_validator(mode="after")
    def _operator_is_the_host(self) -> "LibvirtSettings":
        if self.operator_cidr is None:
            self.operator_cidr = ipaddress.IPv4Network(f"{next(self.public_cidr.hosts())}/32")
        return self
