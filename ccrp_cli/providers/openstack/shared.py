"""The fleet's shared OpenStack resources, created or reused by bootstrap: the common network
(NC) with its subnet and router to the external network, the clones' security group and the
operator key pair. Everything created carries the fleet's Neutron tags."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ...errors import CcrpError

if TYPE_CHECKING:
    from .provider import OpenStackProvider

ROUTER_INTERFACE = "network:router_interface"


def external_network(p: "OpenStackProvider"):
    name = p.settings.external_network
    net = p.find("external network", p.network.find_network, name)
    if net is None or not net.is_router_external:
        raise CcrpError(f"external network {name!r} not found on cloud {p.settings.cloud!r}",
                        hint="set provider.external_network to one of `openstack network list --external`")
    return net


def common_network(p: "OpenStackProvider", create: bool):
    """(network, subnet) of the common network: the inventory's named one, or the fleet's own."""
    cidr = str(p.inv.common.cidr)
    if p.settings.network:
        net = p.find("common network", p.network.find_network, p.settings.network)
        if net is None:
            raise CcrpError(f"network {p.settings.network!r} (provider.network) not found on cloud {p.settings.cloud!r}",
                            hint="create it, or drop provider.network to let ccrp create one")
    else:
        net = next(iter(p.owned("networks", "network")), None)
        if net is None and not create:
            raise CcrpError(f"fleet {p.fleet!r} has no common network yet", hint="run `ccrp fleet up` (it bootstraps the network)")
        if net is None:
            net = p.create_tagged("network", p.network.create_network, p.network.delete_network, p.tags("network"),
                                  name=p.name("common"), description=f"ccrp fleet {p.fleet}: common network")
    subnet = next((s for s in p.listing("subnets", p.network.subnets, network_id=net.id) if s.cidr == cidr), None)
    if subnet is None and p.settings.network:
        raise CcrpError(f"network {p.settings.network!r} has no subnet {cidr} (common.cidr)",
                        hint="set common.cidr to that network's subnet")
    if subnet is None:
        subnet = p.create_tagged("subnet", p.network.create_subnet, p.network.delete_subnet, p.tags("network"),
                                 name=p.name("common"), network_id=net.id, ip_version=4, cidr=cidr)
    return net, subnet


def router(p: "OpenStackProvider", subnet, ext) -> None:
    """The fleet's router from its own common subnet to the external network (floating IPs)."""
    r = next(iter(p.owned("routers", "network")), None)
    if r is None:
        r = p.create_tagged("router", p.network.create_router, p.network.delete_router, p.tags("network"),
                            name=p.name("router"), external_gateway_info={"network_id": ext.id})
    if subnet.id not in router_subnets(p, r):
        # positional: the keyword is subnet_id in openstacksdk 3, subnet in 4
        p.api("add router interface", p.network.add_interface_to_router, r, subnet.id)


def router_subnets(p: "OpenStackProvider", r) -> list[str]:
    ports = p.listing("router ports", p.network.ports, device_id=r.id, device_owner=ROUTER_INTERFACE)
    return [ip["subnet_id"] for port in ports for ip in port.fixed_ips]


def security_group(p: "OpenStackProvider"):
    """The clones' group: ONLY the VPN port from anywhere, SSH from the operator, and everything
    from the common network (topic sharing). Stale ingress rules (an old operator CIDR) go."""
    sg = next(iter(p.owned("security_groups", "network")), None)
    if sg is None:
        sg = p.create_tagged("security group", p.network.create_security_group, p.network.delete_security_group,
                             p.tags("network"), name=p.name("clones"), description=f"ccrp fleet {p.fleet}: clones")
    vpn = p.inv.vpn
    wanted = {
        (vpn.proto, vpn.port, vpn.port, "0.0.0.0/0"),
        ("tcp", 22, 22, str(p.settings.operator_cidr)),
        (None, None, None, str(p.inv.common.cidr)),
    }
    have = {}
    for rule in p.listing("security group rules", p.network.security_group_rules, security_group_id=sg.id):
        if rule.direction == "ingress":
            have[(rule.protocol, rule.port_range_min, rule.port_range_max, rule.remote_ip_prefix)] = rule
    for key, rule in have.items():
        if key not in wanted:
            p.api("delete stale rule", p.network.delete_security_group_rule, rule)
    for proto, lo, hi, prefix in wanted - have.keys():
        p.api("create security group rule", p.network.create_security_group_rule, security_group_id=sg.id,
              direction="ingress", ethertype="IPv4", protocol=proto, port_range_min=lo, port_range_max=hi,
              remote_ip_prefix=prefix, description=f"ccrp fleet {p.fleet}")
    return sg


def key_pair(p: "OpenStackProvider") -> str:
    """The operator's key pair (Nova key pairs carry no tags: the name and key identify it)."""
    name, public = p.name(), p.operator_public_key()
    kp = p.find("key pair", p.compute.find_keypair, name)
    if kp is not None and not same_key(kp.public_key, public):
        raise CcrpError(f"key pair {name!r} exists on cloud {p.settings.cloud!r} with another key",
                        hint="delete it (`openstack keypair delete`) if it is a stale ccrp key, or rename the fleet")
    if kp is None:
        p.api("create key pair", p.compute.create_keypair, name=name, public_key=public)
    return name


def same_key(a: str | None, b: str) -> bool:
    return (a or "").split()[:2] == b.split()[:2]  # type and key; the comment may differ
