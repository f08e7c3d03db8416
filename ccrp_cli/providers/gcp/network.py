"""GCE: the fleet's VPC network, its subnetwork in the region (the common network) and its
firewall rules (the VPN port from anywhere, SSH from the operator's CIDR, the relay between
clones): created when missing, reused when they exist, checked for drift."""

from __future__ import annotations

import ipaddress

from ...errors import CcrpError
from .ownership import tail


class Network:
    """Mixed into GcpProvider: the calls it makes are the provider's (self._call, self.c...)."""

    _subnet_link: str | None  # the provider's (set in GcpProvider.__init__)

    def bootstrap(self) -> None:
        """The VPC network and its subnetwork in the region (the common network), and the
        fleet's firewall rules: create what is missing, reuse what exists."""
        with self._errors(f"bootstrap of fleet {self.fleet} in {self.project}"):
            network = self._ensure_network()
            self._subnet_link = self._ensure_subnetwork(network)
            for rule in self.firewall_rules(network.self_link):
                self._ensure_firewall(rule)

    def _ensure_network(self):
        named = self.settings.network  # type: ignore[union-attr]
        name = named or self.names.network
        network = self._get("network", self.c.networks.get, project=self.project, network=name)
        if network is None and named:
            raise CcrpError(f"network {named!r} not found in project {self.project}",
                            hint="create it, or drop provider.network so ccrp creates its own")
        if network is None:
            self._insert(f"network {name}", self.c.networks.insert, project=self.project,
                         network_resource=self.compute.Network(
                             name=name, auto_create_subnetworks=False, description=self.names.describe("network")))
            network = self._call("get network", self.c.networks.get, project=self.project, network=name)
        elif not named and not self.names.owns_unlabelled(network.name, network.description):
            raise CcrpError(f"network {name} exists but is not ccrp's", hint="name it in provider.network to use it")
        return network

    def _ensure_subnetwork(self, network) -> str:
        """A subnetwork of `network` in the region holding common.cidr: an existing one of a named
        network, else ccrp's own."""
        cidr = self.inv.common.cidr
        subnets = self._list("subnetworks", self.c.subnetworks.list, project=self.project, region=self.region)
        for subnet in subnets:
            if tail(subnet.network) == network.name and cidr.subnet_of(ipaddress.ip_network(subnet.ip_cidr_range)):
                return subnet.self_link
        name = self.names.subnetwork
        self._insert(f"subnetwork {name}", self.c.subnetworks.insert, project=self.project, region=self.region,
                     subnetwork_resource=self.compute.Subnetwork(
                         name=name, network=network.self_link, ip_cidr_range=str(cidr), region=self.region,
                         description=self.names.describe("network")))
        subnet = self._call("get subnetwork", self.c.subnetworks.get, project=self.project, region=self.region,
                            subnetwork=name)
        if subnet.ip_cidr_range != str(cidr) or not self.names.owns_unlabelled(subnet.name, subnet.description):
            raise CcrpError(f"subnetwork {name} exists with range {subnet.ip_cidr_range}, not common.cidr {cidr}",
                            hint="delete it (`ccrp fleet down`) or set common.cidr to its range")
        return subnet.self_link

    def firewall_rules(self, network_link: str) -> list:
        """Ingress to the fleet's instances (network tag ccrp-<fleet>): the VPN port from anywhere,
        SSH from the operator's CIDR, anything from the common network. Nothing else: GCE denies
        other ingress by default, so the ROS master port is never public."""
        vpn, fw = self.inv.vpn, self.compute

        def rule(purpose: str, protocol: str, ports: list[str], source: str):
            return fw.Firewall(
                name=self.names.firewall(purpose), network=network_link, direction="INGRESS", priority=1000,
                allowed=[fw.Allowed(I_p_protocol=protocol, ports=ports)], source_ranges=[source],
                target_tags=[self.names.tag], description=self.names.describe("network"))

        return [
            rule("vpn", vpn.proto, [str(vpn.port)], "0.0.0.0/0"),
            rule("ssh", "tcp", ["22"], str(self.settings.operator_cidr)),  # type: ignore[union-attr]
            rule("common", "all", [], str(self.inv.common.cidr)),
        ]

    @staticmethod
    def _rule_shape(rule) -> tuple:
        return (rule.direction, tail(rule.network), sorted(rule.source_ranges), sorted(rule.target_tags),
                sorted((a.I_p_protocol, tuple(a.ports)) for a in rule.allowed))

    def _ensure_firewall(self, want) -> None:
        have = self._get("firewall", self.c.firewalls.get, project=self.project, firewall=want.name)
        if have is None:
            if self._insert(f"firewall {want.name}", self.c.firewalls.insert, project=self.project,
                            firewall_resource=want):
                return
            have = self._call("get firewall", self.c.firewalls.get, project=self.project, firewall=want.name)
        if not self.names.owns_unlabelled(have.name, have.description):
            raise CcrpError(f"firewall rule {want.name} exists but is not ccrp's", hint="rename or remove it")
        if self._rule_shape(have) != self._rule_shape(want):  # e.g. vpn.port or operator_cidr changed
            self._mutate(f"update firewall {want.name}", self.c.firewalls.update, project=self.project,
                         firewall=want.name, firewall_resource=want)

    def _subnetwork(self) -> str:
        """The common subnetwork's link (bootstrap resolves it; another process may not have)."""
        if self._subnet_link is None:
            self.bootstrap()
        return self._subnet_link  # type: ignore[return-value]
