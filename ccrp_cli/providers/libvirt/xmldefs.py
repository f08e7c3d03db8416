"""The XML ccrp hands libvirt (domains, networks, volumes, the pool), built as element trees, never
as strings with names pasted in, and read back the same way. No libvirt import: the unit tests parse
what is built here.

Ownership: a domain carries the fleet's labels (base.owner_labels) in its <metadata>, under ccrp's
namespace, with the clone's common address. libvirt 9.0 (Debian 12) keeps no metadata on networks
or volumes, so those are ccrp's by name: every one starts with `ccrp-<fleet>-`, and a fleet's name
has no hyphen (models/names.py), so no fleet's prefix is another's."""

from __future__ import annotations

import hashlib
import ipaddress
import xml.etree.ElementTree as ET
from dataclasses import dataclass

NS = "urn:ccrp:libvirt:1"  # the namespace of ccrp's <metadata> element
ET.register_namespace("ccrp", NS)
OWNER = f"{{{NS}}}owner"
LABEL = f"{{{NS}}}label"
# What a clone's serial console is logged to (virtlogd), in the pool's directory: read back through
# the pool like any volume, so a remote libvirt host serves it too.
CONSOLE_SUFFIX = ".console"
GUEST_AGENT = "org.qemu.guest_agent.0"  # the agent's virtio-serial port


def _text(parent: ET.Element, tag: str, text: str, **attrs: str) -> ET.Element:
    el = ET.SubElement(parent, tag, attrs)
    el.text = text
    return el


def dump(el: ET.Element) -> str:
    return ET.tostring(el, encoding="unicode")


def mac_address(*parts: str) -> str:
    """A stable locally administered MAC in QEMU's 52:54:00 range for one interface of one clone:
    the seed's network-config names each interface by it."""
    digest = hashlib.sha256("\0".join(parts).encode()).digest()
    return "52:54:00:" + ":".join(f"{b:02x}" for b in digest[:3])


def bridge_name(fleet: str, role: str) -> str:
    """A Linux bridge name (15 characters at most) for one network of one fleet."""
    return "ccrp" + hashlib.sha256(f"{fleet}\0{role}".encode()).hexdigest()[:8] + role[0]


# -- networks -------------------------------------------------------------------------------------------

# The top of the NAT network is kept out of its DHCP range for simulated robots, which take static
# addresses there (robots.py): this many, or a quarter of a small network.
ROBOT_BLOCK = 16


def robot_block(cidr: ipaddress.IPv4Network) -> list[ipaddress.IPv4Address]:
    """The addresses of the NAT network kept for simulated robots, lowest first."""
    hosts = list(cidr.hosts())
    return hosts[len(hosts) - min(ROBOT_BLOCK, (len(hosts) - 1) // 4):]


def nat_network(name: str, bridge: str, cidr: ipaddress.IPv4Network) -> str:
    """The fleet's public side: NAT to the host's uplink, the host on the first address, DHCP for
    the clones on the rest but the robots' block at the top (robot_block)."""
    net = ET.Element("network")
    _text(net, "name", name)
    ET.SubElement(net, "forward", mode="nat")
    ET.SubElement(net, "bridge", name=bridge, stp="on", delay="0")
    hosts = list(cidr.hosts())
    ip = ET.SubElement(net, "ip", address=str(hosts[0]), netmask=str(cidr.netmask))
    dhcp = ET.SubElement(ip, "dhcp")
    ET.SubElement(dhcp, "range", start=str(hosts[1]), end=str(hosts[-len(robot_block(cidr)) - 1]))
    return dump(net)


def isolated_network(name: str, bridge: str) -> str:
    """The fleet's common network: a bridge with no forward and no host address, so clones reach
    each other on it and nothing else (their addresses are static, from the seed)."""
    net = ET.Element("network")
    _text(net, "name", name)
    ET.SubElement(net, "bridge", name=bridge, stp="on", delay="0")
    return dump(net)


def dhcp_host(mac: str, ip: str, name: str | None = None) -> str:
    """A reservation on the NAT network: the clone's public address is fixed, as a floating IP is,
    across reboots and re-creations (a new machine-id would otherwise get a new lease). No name to
    delete one: libvirt refuses an empty name."""
    return dump(ET.Element("host", {"mac": mac, "ip": ip, **({"name": name} if name else {})}))


def dhcp_hosts(xml: str) -> dict[str, str]:
    """A network's reservations: MAC -> IP."""
    return {h.get("mac", "").lower(): h.get("ip", "") for h in ET.fromstring(xml).findall("ip/dhcp/host")}


# -- storage --------------------------------------------------------------------------------------------

def dir_pool(name: str, path: str) -> str:
    pool = ET.Element("pool", type="dir")
    _text(pool, "name", name)
    target = ET.SubElement(pool, "target")
    _text(target, "path", path)
    return dump(pool)


def pool_path(xml: str) -> str:
    return ET.fromstring(xml).findtext("target/path") or ""


def volume(name: str, capacity: int, fmt: str, backing: str | None = None, backing_fmt: str = "qcow2") -> str:
    """A volume of `capacity` bytes; with `backing`, a copy-on-write overlay of that file (a clone's
    disk costs only its writes)."""
    vol = ET.Element("volume")
    _text(vol, "name", name)
    _text(vol, "capacity", str(capacity), unit="bytes")
    _text(vol, "allocation", "0", unit="bytes")
    target = ET.SubElement(vol, "target")
    ET.SubElement(target, "format", type=fmt)
    if backing:
        store = ET.SubElement(vol, "backingStore")
        _text(store, "path", backing)
        ET.SubElement(store, "format", type=backing_fmt)
    return dump(vol)


# -- domains --------------------------------------------------------------------------------------------

# The golden's kernel command line (also Nova's `os_command_line` for it, scripts/openstack_image.py):
# root is the whole disk (no partition table: the golden volume is one ext4 file system).
KERNEL_CMDLINE = "root=/dev/vda rw console=tty0 console=ttyS0,115200n8"


@dataclass(frozen=True)
class Nic:
    network: str
    mac: str


@dataclass(frozen=True)
class DomainSpec:
    name: str
    title: str
    labels: dict[str, str]
    common_ip: str
    accel: str  # kvm | tcg
    memory_mb: int
    vcpus: int
    pool: str
    disk: str  # volume names in `pool`
    seed: str
    kernel: str  # paths on the libvirt host (the golden volume's kernel and initramfs volumes)
    initrd: str
    console_log: str  # path on the libvirt host
    nics: tuple[Nic, ...]
    cmdline: str = KERNEL_CMDLINE


def domain(spec: DomainSpec) -> str:
    """A persistent VM: direct kernel boot of the golden volume's kernel, its disk an overlay, the
    NoCloud seed a read-only second disk, one virtio NIC per network, the serial console logged to
    a file (the console ccrp pins host keys from), the guest agent's port, a virtio RNG (sshd's keys
    at first boot need entropy, scarce in an emulated guest)."""
    dom = ET.Element("domain", type="kvm" if spec.accel == "kvm" else "qemu")
    _text(dom, "name", spec.name)
    _text(dom, "title", spec.title)
    meta = ET.SubElement(dom, "metadata")
    owner = ET.SubElement(meta, OWNER, {"common-ip": spec.common_ip})
    for key, value in sorted(spec.labels.items()):
        _text(owner, LABEL, value, name=key)
    _text(dom, "memory", str(spec.memory_mb), unit="MiB")
    _text(dom, "vcpu", str(spec.vcpus))
    os_ = ET.SubElement(dom, "os")
    _text(os_, "type", "hvm", arch="x86_64")
    _text(os_, "kernel", spec.kernel)
    _text(os_, "initrd", spec.initrd)
    _text(os_, "cmdline", spec.cmdline)
    ET.SubElement(ET.SubElement(dom, "features"), "acpi")  # `clone stop` is an ACPI power button
    # Under TCG, every instruction set QEMU emulates (`-cpu max`), not its default qemu64: the ROS 2
    # wheels' native code stopped a Jazzy clone's rclpy with SIGILL on qemu64 (measured), while
    # Debian's own packages, built for the x86-64 baseline, ran.
    ET.SubElement(dom, "cpu", mode="host-passthrough" if spec.accel == "kvm" else "maximum")
    _text(dom, "on_poweroff", "destroy")  # autostop's poweroff leaves a stopped (defined) domain
    _text(dom, "on_reboot", "restart")
    _text(dom, "on_crash", "destroy")
    dev = ET.SubElement(dom, "devices")
    for vol, target, fmt, readonly in ((spec.disk, "vda", "qcow2", False), (spec.seed, "vdb", "raw", True)):
        disk = ET.SubElement(dev, "disk", type="volume", device="disk")
        ET.SubElement(disk, "driver", name="qemu", type=fmt)
        ET.SubElement(disk, "source", pool=spec.pool, volume=vol)
        ET.SubElement(disk, "target", dev=target, bus="virtio")
        if readonly:
            ET.SubElement(disk, "readonly")
    for nic in spec.nics:
        iface = ET.SubElement(dev, "interface", type="network")
        ET.SubElement(iface, "source", network=nic.network)
        ET.SubElement(iface, "mac", address=nic.mac)
        ET.SubElement(iface, "model", type="virtio")
    serial = ET.SubElement(dev, "serial", type="pty")
    ET.SubElement(serial, "log", file=spec.console_log, append="on")
    ET.SubElement(serial, "target", port="0")
    console = ET.SubElement(dev, "console", type="pty")
    ET.SubElement(console, "target", type="serial", port="0")
    # QEMU's guest agent (goldens.py): the host sets the clone's clock through it.
    channel = ET.SubElement(dev, "channel", type="unix")
    ET.SubElement(channel, "target", type="virtio", name=GUEST_AGENT)
    rng = ET.SubElement(dev, "rng", model="virtio")
    _text(rng, "backend", "/dev/urandom", model="random")
    ET.SubElement(dev, "memballoon", model="none")
    return dump(dom)


@dataclass(frozen=True)
class DomainInfo:
    """What ccrp reads back from a domain's XML."""

    name: str
    labels: dict[str, str]
    common_ip: str | None
    macs: dict[str, str]  # network -> MAC
    volumes: tuple[str, ...]  # the disks' volume names (pool volumes only)
    memory_mb: int
    vcpus: int


def domain_info(xml: str) -> DomainInfo:
    dom = ET.fromstring(xml)
    owner = dom.find(f"metadata/{OWNER}")
    labels = {el.get("name", ""): el.text or "" for el in owner.findall(LABEL)} if owner is not None else {}
    macs = {}
    for iface in dom.findall("devices/interface"):
        src, mac = iface.find("source"), iface.find("mac")
        network = src.get("network") if src is not None else None
        if network and mac is not None:
            macs[network] = mac.get("address", "").lower()
    vols = tuple(s.get("volume", "") for s in dom.findall("devices/disk/source") if s.get("volume"))
    mem = dom.find("memory")
    scale = {"KiB": 1 / 1024, "MiB": 1, "GiB": 1024}.get(mem.get("unit", "KiB"), 1 / 1024) if mem is not None else 0
    return DomainInfo(name=dom.findtext("name") or "", labels=labels,
                      common_ip=owner.get("common-ip") if owner is not None else None, macs=macs, volumes=vols,
                      memory_mb=int(int(mem.text or 0) * scale) if mem is not None else 0,
                      vcpus=int(dom.findtext("vcpu") or 0))


def probe_domain(name: str, kernel: str, initrd: str, console_log: str, memory_mb: int = 256) -> str:
    """A transient KVM guest with no disk that boots the golden kernel until it looks for its root
    file system: whether KVM really works here (docs/libvirt.md)."""
    dom = ET.Element("domain", type="kvm")
    _text(dom, "name", name)
    _text(dom, "memory", str(memory_mb), unit="MiB")
    _text(dom, "vcpu", "1")
    os_ = ET.SubElement(dom, "os")
    _text(os_, "type", "hvm", arch="x86_64")
    _text(os_, "kernel", kernel)
    _text(os_, "initrd", initrd)
    # No root: the initramfs gives up at once; panic=-1 ends the guest then.
    _text(os_, "cmdline", "console=ttyS0,115200n8 panic=-1 root=/dev/ccrp-probe rootdelay=0")
    ET.SubElement(dom, "cpu", mode="host-passthrough")
    _text(dom, "on_reboot", "destroy")
    _text(dom, "on_crash", "destroy")
    dev = ET.SubElement(dom, "devices")
    serial = ET.SubElement(dev, "serial", type="pty")
    ET.SubElement(serial, "log", file=console_log, append="off")
    ET.SubElement(serial, "target", port="0")
    ET.SubElement(dev, "memballoon", model="none")
    return dump(dom)
