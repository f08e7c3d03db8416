"""The fleet's networks on the libvirt host: its NAT network (the public side: the host reaches the
clones there, each at a DHCP address reserved for its MAC) and its isolated common network, the
storage pool they share with other fleets, the port forwards of robots outside the host
(provider.vpn_forward, forward.py) and the simulated robots' ports on the NAT bridge (robots.py)."""

from __future__ import annotations

import ipaddress
import socket

from ...errors import CcrpError
from ..base import OwnedResource
from . import forward, robots, xmldefs
from .client import LibvirtClient


def bootstrap(c: LibvirtClient) -> None:
    """The storage pool (shared by fleets), the fleet's NAT and isolated networks: created or
    reused, started, set to autostart."""
    public = c.settings.public_cidr
    with c.errors(f"bootstrap of fleet {c.fleet}"):
        c.pool(create=True)
        for name, xml in ((c.public_net, xmldefs.nat_network(c.public_net, xmldefs.bridge_name(c.fleet, "public"), public)),
                          (c.common_net, xmldefs.isolated_network(c.common_net, xmldefs.bridge_name(c.fleet, "common")))):
            net, defined = c.network(name), False
            try:
                if net is None:
                    net, defined = c.api(f"define network {name}", c.conn.networkDefineXML, xml), True
                if not net.isActive():
                    c.api(f"start network {name}", net.create)
            except c.libvirt.libvirtError as exc:
                if defined:  # a network that cannot start ("already in use by interface ...") goes again
                    net.undefine()
                raise CcrpError(f"cannot set up libvirt network {name}: {c.message(exc)}",
                                hint="another network uses that range: change provider.public_cidr") from None
            net.setAutostart(1)


def check_settings(c: LibvirtClient) -> None:
    """What bootstrap refuses before it makes anything: a NAT network over the fleet's other
    ranges, a vpn_forward address that is not this machine's."""
    public = c.settings.public_cidr
    for what, cidr in (("common.cidr", c.inv.common.cidr), ("vpn.pool", c.inv.vpn.pool)):
        if public.overlaps(cidr):
            raise CcrpError(f"provider.public_cidr {public} overlaps {what} {cidr}", hint="change one of them")
    if c.settings.vpn_forward is not None:
        check_forward_address(str(c.settings.vpn_forward.address))


def remove_network(c: LibvirtClient, name: str) -> bool:
    net = c.network(name)
    if net is None:
        return False
    if net.isActive():
        c.api(f"stop network {name}", net.destroy)
    c.api(f"undefine network {name}", net.undefine)
    return True


# -- a clone's public address --------------------------------------------------------------------
def offset(c: LibvirtClient, common_ip: str) -> int:
    """The clone's place in the addressing plan: its common address's offset in common.cidr."""
    pub = c.settings.public_cidr
    found = int(ipaddress.IPv4Address(common_ip)) - int(c.inv.common.cidr.network_address)
    hosts = pub.num_addresses - 2 - len(xmldefs.robot_block(pub))
    if not 2 <= found <= hosts:  # .1 is the host's, the top the simulated robots'
        raise CcrpError(f"clone address {common_ip} has no counterpart in provider.public_cidr {pub}",
                        hint="give provider.public_cidr at least as many addresses as common.cidr")
    return found


def public_ip(c: LibvirtClient, common_ip: str) -> str:
    """The clone's public address: at its common address's offset in provider.public_cidr (the
    addressing plan gives each clone its own), reserved for its MAC on the NAT network."""
    return str(c.settings.public_cidr.network_address + offset(c, common_ip))


def reserve(c: LibvirtClient, mac: str, ip: str, hostname: str) -> None:
    net = c.network(c.public_net)
    if net is None:
        raise CcrpError(f"fleet {c.fleet!r} has no network {c.public_net}", hint="run `ccrp fleet up`")
    have = xmldefs.dhcp_hosts(net.XMLDesc(0))
    if have.get(mac) == ip:
        return
    lv, flags = c.libvirt, c.libvirt.VIR_NETWORK_UPDATE_AFFECT_CONFIG
    flags |= lv.VIR_NETWORK_UPDATE_AFFECT_LIVE if net.isActive() else 0
    if mac in have:
        unreserve(c, mac)
    c.api("reserve the public address", net.update, lv.VIR_NETWORK_UPDATE_COMMAND_ADD_LAST,
          lv.VIR_NETWORK_SECTION_IP_DHCP_HOST, -1, xmldefs.dhcp_host(mac, ip, hostname), flags)


def unreserve(c: LibvirtClient, mac: str) -> None:
    net = c.network(c.public_net)
    if net is None or mac not in (have := xmldefs.dhcp_hosts(net.XMLDesc(0))):
        return
    lv, flags = c.libvirt, c.libvirt.VIR_NETWORK_UPDATE_AFFECT_CONFIG
    flags |= lv.VIR_NETWORK_UPDATE_AFFECT_LIVE if net.isActive() else 0
    c.api("release the public address", net.update, lv.VIR_NETWORK_UPDATE_COMMAND_DELETE,
          lv.VIR_NETWORK_SECTION_IP_DHCP_HOST, -1, xmldefs.dhcp_host(mac, have[mac]), flags)


def reserved(c: LibvirtClient, mac: str) -> str | None:
    net = c.network(c.public_net)
    return xmldefs.dhcp_hosts(net.XMLDesc(0)).get(mac) if net is not None else None


# -- robots outside the host (provider.vpn_forward, forward.py) ------------------------------------
def vpn_forward(c: LibvirtClient, robot: str, common_ip: str | None) -> forward.Forward | None:
    fwd = c.settings.vpn_forward
    if fwd is None or not common_ip:
        return None
    return forward.Forward(c.fleet, robot, str(fwd.address), fwd.base_port + offset(c, common_ip),
                           public_ip(c, common_ip), c.inv.vpn.port, c.inv.vpn.proto)


def check_forward_address(address: str) -> None:
    """vpn_forward.address must be this machine's: robots' packets to it are the ones forwarded."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((address, 0))
        except OSError:
            raise CcrpError(f"provider.vpn_forward.address {address} is not an address of this machine",
                            hint="give the libvirt host's address on the robots' LAN (`ip -4 address`)") from None


def forwards(c: LibvirtClient) -> list[OwnedResource]:
    """The fleet's port forwards, one per robot. Listed only where they can be (this machine's
    firewall, root): with vpn_forward unset, a forward left by an earlier inventory is still found."""
    if not c.local:
        return []
    try:
        rules = forward.listed(c.fleet)
    except CcrpError:
        if c.settings.vpn_forward is not None:
            raise
        return []
    robots_seen = sorted({forward.robot_of(spec) for _table, spec in rules})
    return [OwnedResource(kind="port_forward", id=forward.comment(c.fleet, r), name=forward.comment(c.fleet, r), robot=r)
            for r in robots_seen]


# -- simulated robots' ports on the NAT network (robots.py) ----------------------------------------
def robot_port(c: LibvirtClient, robot: str, index: int) -> robots.RobotPort:
    """The port of robot `robot` (addressing slot `index`) on the fleet's NAT network: refused
    in one line unless the libvirt host is this machine or the network is missing."""
    robots.require_local(c.settings.uri)
    with c.errors(f"network {c.public_net}"):
        net = c.network(c.public_net)
        if net is None or not net.isActive():
            raise CcrpError(f"fleet {c.fleet!r} has no running network {c.public_net}", hint="run `ccrp fleet up`")
        taken = set(xmldefs.dhcp_hosts(net.XMLDesc(0)).values())
        taken |= {lease.get("ipaddr", "") for lease in net.DHCPLeases()}
        bridge = net.bridgeName()
    cidr = c.settings.public_cidr
    address = robots.robot_address(cidr, index, taken, robot)
    return robots.RobotPort(network=c.public_net, bridge=bridge, veth=robots.veth_name(c.fleet, robot),
                            address=ipaddress.IPv4Interface(f"{address}/{cidr.prefixlen}"))


def release_robot_port(c: LibvirtClient, robot: str) -> None:
    if c.local:
        robots.release(c.fleet, robot)
