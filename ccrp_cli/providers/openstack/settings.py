"""`provider:` of an inventory for an OpenStack cloud."""

from __future__ import annotations

import ipaddress
from typing import Literal

from ...models.strict import ProviderSettings
from ...models.values import CloudName


class OpenStackSettings(ProviderSettings):
    kind: Literal["openstack"]
    cloud: CloudName  # entry in clouds.yaml (or OS_CLOUD); never parsed by ccrp
    flavor: CloudName
    image: CloudName | None = None
    network: CloudName | None = None  # existing common network; created when absent
    external_network: CloudName = "public"
    operator_cidr: ipaddress.IPv4Network
    zones: list[CloudName] = []

    def place(self) -> str:
        return self.cloud

    def operator_network(self) -> ipaddress.IPv4Network | None:
        return self.operator_cidr

    def bake_image(self) -> str | None:
        return self.image
