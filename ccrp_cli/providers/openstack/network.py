"""The fleet's shared OpenStack resources, created or reused by bootstrap: the common network
(NC) with its subnet and router to the external network, the clones' security group and the
operator key pair. Everything created carries the fleet's Neutron tags."""

from __future__ import annotations

from ...errors import CcrpError
from ...models.addressing import capacity
from .client import OpenStackClient

ROUTER_INTERFACE = "network:router_interface"


def bootstrap(c: OpenStackClient, public_key: str) -> None:
    """The fleet's network resources, created or reused, and kept for its clones' creation."""
    with c.errors(f"bootstrap of fleet {c.fleet}"):
        ext = external_network(c)
        net, subnet = common_network(c, create=True)
        if not c.settings.network:  # a named network is the operator's, already routed
            router(c, subnet, ext)
        sg = security_group(c)
        if c.settings.entry == "gateway":
            c.remember(gsg=gateway_security_group(c))
        key_pair(c, public_key)
        c.remember(ext=ext, net=(net, subnet), sg=sg)


def fleet_resources(c: OpenStackClient):
    """(external network, common network, its subnet, the clones' security group), looked up once."""
    ext = c.cached("ext", lambda: external_network(c))
    net, subnet = c.cached("net", lambda: common_network(c, create=False))
    sg = c.cached("sg", lambda: next(iter(c.tagged("security_groups", "network")), None))
    if sg is None:
        raise CcrpError(f"fleet {c.fleet!r} has no security group yet", hint="run `ccrp fleet up`")
    return ext, net, subnet, sg


def gateway_group(c: OpenStackClient):
    """The entry gateway's security group, looked up once."""
    sg = c.cached("gsg", lambda: next(iter(c.tagged("security_groups", "gateway")), None))
    if sg is None:
        raise CcrpError(f"fleet {c.fleet!r} has no gateway security group yet", hint="run `ccrp fleet up`")
    return sg


def external_network(c: OpenStackClient):
    name = c.settings.external_network
    net = c.find("external network", c.network.find_network, name)
    if net is None or not net.is_router_external:
        raise CcrpError(f"external network {name!r} not found on cloud {c.settings.cloud!r}",
                        hint="set provider.external_network to one of `openstack network list --external`")
    return net


def common_network(c: OpenStackClient, create: bool):
    """(network, subnet) of the common network: the inventory's named one, or the fleet's own."""
    cidr = str(c.inv.common.cidr)
    if c.settings.network:
        net = c.find("common network", c.network.find_network, c.settings.network)
        if net is None:
            raise CcrpError(f"network {c.settings.network!r} (provider.network) not found on cloud {c.settings.cloud!r}",
                            hint="create it, or drop provider.network to let ccrp create one")
    else:
        net = next(iter(c.tagged("networks", "network")), None)
        if net is None and not create:
            raise CcrpError(f"fleet {c.fleet!r} has no common network yet", hint="run `ccrp fleet up` (it bootstraps the network)")
        if net is None:
            net = c.create_tagged("network", c.network.create_network, c.network.delete_network, c.tags("network"),
                                  name=c.name("common"), description=f"ccrp fleet {c.fleet}: common network")
    subnet = next((s for s in c.listing("subnets", c.network.subnets, network_id=net.id) if s.cidr == cidr), None)
    if subnet is None and c.settings.network:
        raise CcrpError(f"network {c.settings.network!r} has no subnet {cidr} (common.cidr)",
                        hint="set common.cidr to that network's subnet")
    if subnet is None:
        subnet = c.create_tagged("subnet", c.network.create_subnet, c.network.delete_subnet, c.tags("network"),
                                 name=c.name("common"), network_id=net.id, ip_version=4, cidr=cidr)
    return net, subnet


def router(c: OpenStackClient, subnet, ext) -> None:
    """The fleet's router from its own common subnet to the external network (floating IPs)."""
    r = next(iter(c.tagged("routers", "network")), None)
    if r is None:
        r = c.create_tagged("router", c.network.create_router, c.network.delete_router, c.tags("network"),
                            name=c.name("router"), external_gateway_info={"network_id": ext.id})
    if subnet.id not in router_subnets(c, r):
        # positional: the keyword is subnet_id in openstacksdk 3, subnet in 4
        c.api("add router interface", c.network.add_interface_to_router, r, subnet.id)


def router_subnets(c: OpenStackClient, r) -> list[str]:
    ports = c.listing("router ports", c.network.ports, device_id=r.id, device_owner=ROUTER_INTERFACE)
    return [ip["subnet_id"] for port in ports for ip in port.fixed_ips]


def security_group(c: OpenStackClient):
    """The clones' group: the VPN port from anywhere (from the gateway only, behind an entry
    gateway: everything from the common network), SSH from the operator, and everything from the
    common network (topic sharing). Stale ingress rules (an old operator CIDR) go."""
    vpn = c.inv.vpn
    wanted = {("tcp", 22, 22, str(c.settings.operator_cidr)), (None, None, None, str(c.inv.common.cidr))}
    if c.settings.entry != "gateway":
        wanted.add((vpn.proto, vpn.port, vpn.port, "0.0.0.0/0"))
    return _group(c, "network", "clones", wanted)


def gateway_security_group(c: OpenStackClient):
    """The entry gateway's group: the robots' ports (render/gateway.py) from anywhere, SSH from the
    operator; nothing else (its replies and what it forwards are the connections' own)."""
    vpn = c.inv.vpn
    wanted = {(vpn.proto, vpn.port + 1, vpn.port + capacity(c.inv), "0.0.0.0/0"),
              ("tcp", 22, 22, str(c.settings.operator_cidr))}
    return _group(c, "gateway", "gateway", wanted)


def _group(c: OpenStackClient, role: str, name: str, wanted: set):
    """The fleet's security group of `role`, made if missing, with exactly the ingress rules
    `wanted` ((protocol, first port, last port, remote prefix))."""
    sg = next(iter(c.tagged("security_groups", role)), None)
    if sg is None:
        sg = c.create_tagged("security group", c.network.create_security_group, c.network.delete_security_group,
                             c.tags(role), name=c.name(name), description=f"ccrp fleet {c.fleet}: {name}")
    have = {}
    for rule in c.listing("security group rules", c.network.security_group_rules, security_group_id=sg.id):
        if rule.direction == "ingress":
            have[(rule.protocol, rule.port_range_min, rule.port_range_max, rule.remote_ip_prefix)] = rule
    for key, rule in have.items():
        if key not in wanted:
            c.api("delete stale rule", c.network.delete_security_group_rule, rule)
    for proto, lo, hi, prefix in wanted - have.keys():
        c.api("create security group rule", c.network.create_security_group_rule, security_group_id=sg.id,
              direction="ingress", ethertype="IPv4", protocol=proto, port_range_min=lo, port_range_max=hi,
              remote_ip_prefix=prefix, description=f"ccrp fleet {c.fleet}")
    return sg


def key_pair(c: OpenStackClient, public: str) -> str:
    """The operator's key pair (Nova key pairs carry no tags: the name and key identify it)."""
    name = c.name()
    kp = c.find("key pair", c.compute.find_keypair, name)
    if kp is not None and not same_key(kp.public_key, public):
        raise CcrpError(f"key pair {name!r} exists on cloud {c.settings.cloud!r} with another key",
                        hint="delete it (`openstack keypair delete`) if it is a stale ccrp key, or rename the fleet")
    if kp is None:
        c.api("create key pair", c.compute.create_keypair, name=name, public_key=public)
    return name


def same_key(a: str | None, b: str) -> bool:
    return (a or "").split()[:2] == b.split()[:2]  # type and key; the comment may differ
