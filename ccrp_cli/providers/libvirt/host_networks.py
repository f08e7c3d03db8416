"""`ccrp init`'s scan of this host (ProviderInfo.host_networks): the local libvirt daemon's network
definitions, running or not: a stopped one (libvirt's `default`, 192.168.122.0/24) has no route
yet, but clashes as soon as it starts."""

from __future__ import annotations

import ipaddress
import xml.etree.ElementTree as ET
from pathlib import Path

NETWORKS = "/etc/libvirt/qemu/networks"


def defined() -> dict[str, str]:
    """Range -> "libvirt network NAME", read from the definitions' files (no daemon asked)."""
    ranges: dict[str, str] = {}
    for path in sorted(Path(NETWORKS).glob("*.xml")):
        try:
            for ip in ET.parse(path).getroot().iter("ip"):
                if ip.get("family", "ipv4") == "ipv4" and ip.get("address"):
                    net = ipaddress.IPv4Network(f"{ip.get('address')}/{ip.get('prefix') or ip.get('netmask') or 24}",
                                                strict=False)
                    ranges[str(net)] = f"libvirt network {path.stem}"
        except (OSError, ET.ParseError, ValueError):
            pass
    return ranges
