"""Simulated robots of a libvirt fleet (Ability.ROBOT_ATTACH): a robot is a container of this
host's Docker engine, as for a cloud fleet, but with no Docker network. It gets one veth pair
instead: the host end a port of the fleet's NAT network's bridge, the other its eth0, with a static
address from the top of the NAT subnet (xmldefs.robot_block, outside the DHCP range). So it reaches
its clone's public address as a robot on the clone's LAN would, and the clone's firewall sees it as
any robot: only the VPN port is open to it.

No default route: the robot needs nothing beyond the NAT subnet, and with one via the host (tried
first) its demo node's first call to the master, made before the tunnel was up, went to the host's
egress, where this machine's transparent proxy accepted the connection and held it: the node never
registered (measured: 10 minutes). Without one, that call fails at once and rospy tries again.

Why not the NAT network's DHCP or a Docker network: libvirt's firewall rejects new connections
from outside into a NAT network (only the host may open them), and a Docker bridge network is
another subnet behind that rule. A port on the bridge itself is inside.

The veth's other end lives in the container's network namespace, so removing the container should
remove the pair; `robot sim --stop`, `fleet down` and `gc` still delete the host end (release): one
outlived its container by minutes here, its namespace not yet freed. Only on the libvirt host itself (a local URI):
the bridge must be on this machine. Commands are argument lists (`ip`, `nsenter`), never a shell."""

from __future__ import annotations

import hashlib
import ipaddress
import subprocess
from dataclasses import dataclass

from ...errors import CcrpError
from . import xmldefs
from .settings import LOCAL_URIS
# The robot's interface in its own network namespace (which has only lo before it).
GUEST_IF = "eth0"


def require_local(uri: str) -> None:
    """One line when the libvirt host is another machine: its NAT bridge is not here."""
    if uri not in LOCAL_URIS:
        raise CcrpError(f"simulated robots sit on the fleet's NAT network, which is on the libvirt host, and "
                        f"provider.uri {uri} is not this machine",
                        hint="run `ccrp robot sim` on the libvirt host (uri qemu:///system), or connect a real robot: docs/libvirt.md")


def veth_name(fleet: str, robot: str) -> str:
    """The host end's name (15 characters at most), one per fleet and robot."""
    return "ccrpv" + hashlib.sha256(f"{fleet}\0{robot}".encode()).hexdigest()[:10]


def robot_address(cidr: ipaddress.IPv4Network, index: int, taken: set[str], robot: str) -> ipaddress.IPv4Address:
    """The robot of slot `index` (1, 2, ...: state's addressing slot) gets the `index`-th address
    from the top of the NAT network. `taken`: addresses reserved or leased there (a network made
    before the robots' block existed hands those out too)."""
    block = xmldefs.robot_block(cidr)
    if not 1 <= index <= len(block):
        raise CcrpError(f"robot {robot!r} (slot {index}) has no simulated robot address: the NAT network {cidr} "
                        f"keeps {len(block)} at its top", hint="simulate fewer robots at once, or a larger provider.public_cidr")
    address = block[-index]
    if str(address) in taken:
        raise CcrpError(f"{address}, simulated robot {robot!r}'s address on {cidr}, is leased or reserved there",
                        hint="ccrp fleet down and up makes the network again with the robots' block kept out of DHCP")
    return address


@dataclass(frozen=True)
class RobotPort:
    """The simulated robot's port on the fleet's NAT network."""

    network: str  # the libvirt network's name
    bridge: str
    veth: str  # the host end
    address: ipaddress.IPv4Interface

    def __str__(self) -> str:
        return f"{self.network} ({self.address.ip})"

    def attach(self, pid: int) -> None:
        """Give the network namespace of process `pid` (the container's) its port."""
        ns = ["nsenter", "--target", str(pid), "--net", "--"]
        _run(["ip", "link", "del", self.veth], ok_missing=True)  # left by a robot whose container died mid-start
        try:
            _run(["ip", "link", "add", self.veth, "type", "veth", "peer", "name", GUEST_IF, "netns", str(pid)])
            _run(["ip", "link", "set", self.veth, "master", self.bridge, "up"])
            _run([*ns, "ip", "address", "add", str(self.address), "dev", GUEST_IF])
            _run([*ns, "ip", "link", "set", GUEST_IF, "up"])  # its only route: the NAT subnet, on link
        except CcrpError:
            _run(["ip", "link", "del", self.veth], ok_missing=True)
            raise


def release(fleet: str, robot: str) -> None:
    """Delete the host end of the robot's port if it is still there (its peer goes with it)."""
    _run(["ip", "link", "del", veth_name(fleet, robot)], ok_missing=True)


def _run(argv: list[str], ok_missing: bool = False) -> None:
    try:
        proc = subprocess.run(argv, capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise CcrpError(f"cannot run {argv[0]}: {exc}", hint="the robot's port needs iproute2 and util-linux (nsenter)") from None
    if proc.returncode != 0 and not (ok_missing and "Cannot find device" in proc.stderr):
        raise CcrpError(f"`{' '.join(argv)}` failed: {' '.join(proc.stderr.split())[-200:]}")
