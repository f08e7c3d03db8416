"""`provider:` of an inventory for Amazon EC2."""

from __future__ import annotations

import ipaddress
from typing import Literal

from ...models.strict import Strict


class AwsSettings(Strict):
    kind: Literal["aws"]
    region: str
    profile: str | None = None
    instance_type: str = "t3.medium"
    vpc_id: str | None = None
    zones: list[str] = []
    operator_cidr: ipaddress.IPv4Network
