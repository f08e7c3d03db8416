"""`provider:` of an inventory for an OpenStack cloud."""

from __future__ import annotations

import ipaddress
from typing import Literal

from ...models.strict import Strict


class OpenStackSettings(Strict):
    kind: Literal["openstack"]
    cloud: str  # entry in clouds.yaml (or OS_CLOUD); never parsed by ccrp
    flavor: str
    image: str | None = None
    network: str | None = None  # existing common network; created when absent
    external_network: str = "public"
    operator_cidr: ipaddress.IPv4Network
    zones: list[str] = []
