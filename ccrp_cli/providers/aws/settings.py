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

    def place(self) -> str:
        return self.region

    def operator_network(self) -> ipaddress.IPv4Network | None:
        return self.operator_cidr
