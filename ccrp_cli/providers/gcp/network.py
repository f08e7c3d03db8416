"""GCE: the fleet's VPC network, its subnetwork in the region (the common network) and its
firewall rules (the VPN port from anywhere, SSH from the operator's CIDR, the relay between
clones): created when missing, reused when they exist, checked for drift."""

from __future__ import annotations

import ipaddress

from ...errors import CcrpError
from ...models.addressing import capacity
from ..base import GATEWAY
from .client import GcpClient
from .ownership import tail


def bootstrap(c: GcpClient) -> None:
    """The VPC network and its subnetwork in the region (the common network), and the
    fleet's firewall rules: create what is missing, reuse what exists."""
    with c.errors(f"bootstrap of fleet {c.fleet} in {c.project}"):
        network = ensure_network(c)
        c.subnet_link = ensure_subnetwork(c, network)
        for rule in firewall_rules(c, network.self_link):
            ensure_firewall(c, rule)


def ensure_network(c: GcpClient):
    named = c.settings.network
    name = named or c.names.network
    network = c.get("network", c.clients.networks.get, project=c.project, network=name)
    if network is None and named:
        raise CcrpError(f"network {named!r} not found in project {c.project}",
                        hint="create it, or drop provider.network so ccrp creates its own")
    if network is None:
        c.insert(f"network {name}", c.clients.networks.insert, project=c.project,
                     network_resource=c.compute.Network(
                         name=name, auto_create_subnetworks=False, description=c.names.describe("network")))
        network = c.call("get network", c.clients.networks.get, project=c.project, network=name)
    elif not named and not c.names.owns_unlabelled(network.name, network.description):
        raise CcrpError(f"network {name} exists but is not ccrp's", hint="name it in provider.network to use it")
    return network


def ensure_subnetwork(c: GcpClient, network) -> str:
    """A subnetwork of `network` in the region holding common.cidr: an existing one of a named
    network, else ccrp's own."""
    cidr = c.inv.common.cidr
    subnets = c.list("subnetworks", c.clients.subnetworks.list, project=c.project, region=c.region)
    for subnet in subnets:
        if tail(subnet.network) == network.name and cidr.subnet_of(ipaddress.IPv4Network(subnet.ip_cidr_range)):
            return subnet.self_link
    name = c.names.subnetwork
    c.insert(f"subnetwork {name}", c.clients.subnetworks.insert, project=c.project, region=c.region,
                 subnetwork_resource=c.compute.Subnetwork(
                     name=name, network=network.self_link, ip_cidr_range=str(cidr), region=c.region,
                     description=c.names.describe("network")))
    subnet = c.call("get subnetwork", c.clients.subnetworks.get, project=c.project, region=c.region,
                        subnetwork=name)
    if subnet.ip_cidr_range != str(cidr) or not c.names.owns_unlabelled(subnet.name, subnet.description):
        raise CcrpError(f"subnetwork {name} exists with range {subnet.ip_cidr_range}, not common.cidr {cidr}",
                        hint="delete it (`ccrp fleet down`) or set common.cidr to its range")
    return subnet.self_link


def firewall_rules(c: GcpClient, network_link: str) -> list:
    """Ingress to the fleet's clones (network tag ccrp-<fleet>): the VPN port from anywhere, SSH
    from the operator's CIDR, anything from the common network. Behind an entry gateway (tag
    ccrp-<fleet>-gateway) the clones' VPN port and SSH are the common network's only (the gateway
    forwards both), and the gateway admits the robots' ports (render/gateway.py) from anywhere, SSH
    from the operator and anything from the clones (their way out). Nothing else: GCE denies other
    ingress by default, so the ROS master port is never public."""
    vpn, fw, operator, common = c.inv.vpn, c.compute, str(c.settings.operator_cidr), str(c.inv.common.cidr)
    gateway = c.settings.entry == "gateway"

    def rule(purpose: str, protocol: str, ports: list[str], source: str, tags: list[str] | None = None, robot=None):
        return fw.Firewall(
            name=c.names.firewall(purpose), network=network_link, direction="INGRESS", priority=1000,
            allowed=[fw.Allowed(I_p_protocol=protocol, ports=ports)], source_ranges=[source],
            target_tags=tags or [c.names.tag], description=c.names.describe("network", robot))

    rules = [
        rule("vpn", vpn.proto, [str(vpn.port)], common if gateway else "0.0.0.0/0"),
        rule("ssh", "tcp", ["22"], common if gateway else operator),
        rule("common", "all", [], common, [c.names.tag, c.names.gateway_tag] if gateway else None),
    ]
    if gateway:
        rules += [rule("gateway-robots", vpn.proto, [f"{vpn.port + 1}-{vpn.port + capacity(c.inv)}"], "0.0.0.0/0",
                       [c.names.gateway_tag], GATEWAY),
                  rule("gateway-ssh", "tcp", ["22"], operator, [c.names.gateway_tag], GATEWAY)]
    return rules


def rule_shape(rule) -> tuple:
    return (rule.direction, tail(rule.network), sorted(rule.source_ranges), sorted(rule.target_tags),
            sorted((a.I_p_protocol, tuple(a.ports)) for a in rule.allowed))


def ensure_firewall(c: GcpClient, want) -> None:
    have = c.get("firewall", c.clients.firewalls.get, project=c.project, firewall=want.name)
    if have is None:
        if c.insert(f"firewall {want.name}", c.clients.firewalls.insert, project=c.project,
                        firewall_resource=want):
            return
        have = c.call("get firewall", c.clients.firewalls.get, project=c.project, firewall=want.name)
    if not c.names.owns_unlabelled(have.name, have.description):
        raise CcrpError(f"firewall rule {want.name} exists but is not ccrp's", hint="rename or remove it")
    if rule_shape(have) != rule_shape(want):  # e.g. vpn.port or operator_cidr changed
        c.mutate(f"update firewall {want.name}", c.clients.firewalls.update, project=c.project,
                     firewall=want.name, firewall_resource=want)


def subnetwork(c: GcpClient) -> str:
    """The common subnetwork's link (bootstrap resolves it; another process may not have)."""
    if c.subnet_link is None:
        bootstrap(c)
    return c.subnet_link  # type: ignore[return-value]
