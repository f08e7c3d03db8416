"""`provider:` of an inventory for Google Compute Engine."""

from __future__ import annotations

import ipaddress
from typing import Literal

from ...models.strict import ProviderSettings
from ...models.values import CloudName


class GcpSettings(ProviderSettings):
    kind: Literal["gcp"]
    project: CloudName
    region: CloudName
    zones: list[CloudName]
    machine_type: CloudName = "e2-medium"
    network: CloudName | None = None
    operator_cidr: ipaddress.IPv4Network
    # A new project has 8 external addresses per region: one per fleet by default (docs/gcp.md).
    entry: Literal["per-clone", "gateway"] = "gateway"
    gateway_machine_type: CloudName = "e2-micro"  # the entry gateway only forwards packets

    def place(self) -> str:
        return self.region

    def operator_network(self) -> ipaddress.IPv4Network | None:
        return self.operator_cidr
