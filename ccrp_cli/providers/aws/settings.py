"""`provider:` of an inventory for Amazon EC2."""

from __future__ import annotations

import ipaddress
from typing import Literal

from ...models.strict import ProviderSettings
from ...models.values import CloudName


class AwsSettings(ProviderSettings):
    kind: Literal["aws"]
    region: CloudName
    profile: CloudName | None = None
    instance_type: CloudName = "t3.medium"
    vpc_id: CloudName | None = None
    zones: list[CloudName] = []
    operator_cidr: ipaddress.IPv4Network
    # One public address per fleet (docs/aws.md "Entry gateway"): a new account has 5 Elastic IPs
    # a region, and AWS bills every public IPv4. `per-clone` gives each clone its own.
    entry: Literal["per-clone", "gateway"] = "gateway"
    # The entry gateway's public subnet (its Elastic IP's interface, routed to the internet
    # gateway); the clones' subnet is common.cidr, routed out through the gateway. Outside the
    # VPC's blocks it is added to the VPC as a second CIDR block (100.64.0.0/10 may be added to a
    # VPC of any private range).
    gateway_cidr: ipaddress.IPv4Network = ipaddress.IPv4Network("100.64.0.0/28")
    gateway_instance_type: CloudName = "t3.micro"  # it only forwards packets

    def place(self) -> str:
        return self.region

    def operator_network(self) -> ipaddress.IPv4Network | None:
        return self.operator_cidr

    def networks(self) -> dict[str, ipaddress.IPv4Network]:
        return {"provider.gateway_cidr": self.gateway_cidr} if self.entry == "gateway" else {}
