"""The fleet address plan: a VPN subnet per clone, a common-network address, hostnames.

Slots (indexes) are allocated once per robot and recorded in state, so removing a robot never
shifts another robot's addresses.
"""

from __future__ import annotations

import ipaddress

from dataclasses import dataclass
from functools import cached_property

from ..errors import InputError
from .inventory import Inventory
from .names import clone_host


@dataclass(frozen=True)
class CloneAddresses:
    robot: str
    index: int
    clone_host: str
    vpn_subnet: ipaddress.IPv4Network
    clone_vpn_ip: ipaddress.IPv4Address  # .1 of the subnet
    robot_vpn_ip: ipaddress.IPv4Address  # .2: the robot's fixed address
    device_vpn_ip: ipaddress.IPv4Address  # .3: its power device's (docs/dashboard.md, Robot power)
    common_ip: ipaddress.IPv4Address

    @cached_property
    def hosts_line(self) -> str:
        """This clone's line in /etc/hosts of every other clone: made once per address plan, which
        every clone's render shares."""
        return f"{str(self.common_ip):<15} {self.clone_host}\n"


def capacity(inv: Inventory) -> int:
    """How many clones the pools can address (and, behind an entry gateway, its ports: entry_port)."""
    vpn_slots = 2 ** (inv.vpn.subnet_prefix - inv.vpn.pool.prefixlen) - 1  # slot 0 is kept free
    common_slots = inv.common.cidr.num_addresses - 1 - inv.common.first_host  # minus broadcast
    ports = 65535 - inv.vpn.port if inv.provider.entry == "gateway" else common_slots
    return max(0, min(vpn_slots, common_slots, ports))


def allocate(inv: Inventory, robots: list[str], existing: dict[str, int]) -> dict[str, int]:
    """Return slot indexes for `robots`: existing ones kept, new ones get the lowest free slot."""
    result = {name: existing[name] for name in robots if name in existing}
    used = set(existing.values())
    limit = capacity(inv)
    slot = 1
    for name in robots:
        if name in result:
            continue
        while slot in used:
            slot += 1
        if slot > limit:
            raise InputError(
                f"address pools are exhausted: {len(robots)} clones requested, room for {limit} "
                f"(vpn.pool {inv.vpn.pool} in /{inv.vpn.subnet_prefix} subnets, common.cidr {inv.common.cidr}"
                + (f", gateway ports from vpn.port {inv.vpn.port} + 1 to 65535" if inv.provider.entry == "gateway" else "") + ")",
                hint="widen vpn.pool or common.cidr in the inventory" + (", or lower vpn.port" if inv.provider.entry == "gateway" else ""),
            )
        result[name] = slot
        used.add(slot)
    return result


def addresses(inv: Inventory, robot: str, index: int) -> CloneAddresses:
    subnet_size = 2 ** (32 - inv.vpn.subnet_prefix)
    subnet = ipaddress.IPv4Network(
        (int(inv.vpn.pool.network_address) + index * subnet_size, inv.vpn.subnet_prefix)
    )
    return CloneAddresses(
        robot=robot,
        index=index,
        clone_host=clone_host(robot),
        vpn_subnet=subnet,
        clone_vpn_ip=subnet.network_address + 1,
        robot_vpn_ip=subnet.network_address + 2,
        device_vpn_ip=subnet.network_address + 3,
        common_ip=inv.common.cidr.network_address + inv.common.first_host + index - 1,
    )


# Two fixed hosts below the clones' range, for the instances that are not clones; near the top of the
# subnet when the low addresses are the ones clouds keep for routers and DHCP (AWS keeps .1-.3, GCP
# the second-to-last).
def builder_ip(inv: Inventory) -> ipaddress.IPv4Address:
    """The `snapshot bake` builder's address on the common network: just below the first clone's."""
    net, first = inv.common.cidr, inv.common.first_host
    return net.network_address + first - 1 if first - 1 >= 4 else net.broadcast_address - 2


def gateway_ip(inv: Inventory) -> ipaddress.IPv4Address:
    """The entry gateway's address on the common network, just below the builder's (a bake runs
    while the fleet's gateway does). Fixed like the clones', so a gateway re-created is the same hop."""
    net, first = inv.common.cidr, inv.common.first_host
    return net.network_address + first - 2 if first - 2 >= 4 else net.broadcast_address - 3


def entry_port(inv: Inventory, index: int) -> int:
    """The port a robot dials on its fleet's entry gateway: the VPN port plus the robot's slot. The
    slot is the robot's for its life and never given to another while it exists, so the port is too."""
    return inv.vpn.port + index
