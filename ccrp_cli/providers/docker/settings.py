"""`provider:` of an inventory for The local Docker backend."""

from __future__ import annotations

import ipaddress
from typing import Literal

from ...models.strict import ProviderSettings
from ...models.values import DockerImage


class DockerSettings(ProviderSettings):
    kind: Literal["docker"]
    # Subnet of the <fleet>-public Docker network (plays the clouds' public network).
    public_cidr: ipaddress.IPv4Network = ipaddress.IPv4Network("172.30.0.0/24")
    # Publish each clone's VPN port on the host so a real robot on the LAN can connect.
    publish_vpn_ports: bool = False
    # The generated Dockerfile's FROM line (templates/docker/Dockerfile.j2): a reference, one token.
    base_image: DockerImage = "ccrp/base:bookworm"

    def networks(self) -> dict[str, ipaddress.IPv4Network]:
        return {"provider.public_cidr": self.public_cidr}
