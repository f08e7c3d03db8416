"""The fleet's Docker networks on this host: <fleet>-public (the clones' and simulated robots' LAN)
and <fleet>-common (internal: the clones' common network), created or reused by bootstrap."""

from __future__ import annotations

from typing import cast

from ...errors import CcrpError
from ...models.inventory import Inventory
from ..base import LABEL_FLEET, owner_labels
from .client import DockerHost
from .settings import DockerSettings


def bootstrap(c: DockerHost, inv: Inventory) -> None:
    """Create (or reuse) the fleet's public and common networks."""
    from docker.types import IPAMConfig, IPAMPool

    provider = cast(DockerSettings, inv.provider)  # the fleet's backend is this one
    for name, cidr, internal in (
        (c.public_net, provider.public_cidr, False),
        (c.common_net, inv.common.cidr, True),
    ):
        existing = c.engine.networks.list(names=[name])
        existing = [n for n in existing if n.name == name]
        if existing:
            if existing[0].attrs.get("Labels", {}).get(LABEL_FLEET) != c.fleet:
                raise CcrpError(f"Docker network {name} exists and is not ccrp's", hint="remove or rename it")
            continue
        try:
            c.engine.networks.create(
                name, driver="bridge", internal=internal, labels=owner_labels(c.fleet, "network"),
                ipam=IPAMConfig(pool_configs=[IPAMPool(subnet=str(cidr))]),
            )
        except c.APIError as exc:
            raise CcrpError(
                f"cannot create Docker network {name} ({cidr}): {exc.explanation}",
                hint="another network uses that subnet: change provider.public_cidr or common.cidr",
            ) from None
