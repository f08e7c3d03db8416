"""`provider:` of an inventory for Google Compute Engine."""

from __future__ import annotations

import ipaddress
from typing import Literal

from ...models.strict import Strict


class GcpSettings(Strict):
    kind: Literal["gcp"]
    project: str
    region: str
    zones: list[str]
    machine_type: str = "e2-medium"
    network: str | None = None
    operator_cidr: ipaddress.IPv4Network
