"""`ccrp init`'s scan of this host (ProviderInfo.host_networks): the IPv4 subnets of its Docker
networks, which a new fleet's pools must not overlap."""

from __future__ import annotations

import ipaddress

from ..sdk import docker_module


def subnets() -> dict[str, str]:
    """Subnet -> "Docker network NAME" (none when no engine answers)."""
    try:
        client = docker_module().from_env(timeout=5)
    except Exception:  # noqa: BLE001 - no engine here: nothing of Docker's to avoid
        return {}
    try:
        return {str(ipaddress.IPv4Network(cfg["Subnet"], strict=False)): f"Docker network {net.name}" for net in client.networks.list()
                for cfg in (net.attrs.get("IPAM") or {}).get("Config") or [] if ":" not in cfg.get("Subnet", ":")}
    except Exception:  # noqa: BLE001 - same
        return {}
    finally:
        client.close()
