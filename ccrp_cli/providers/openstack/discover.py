"""`ccrp init --provider openstack --cloud NAME`: the `provider:` values read from the cloud itself,
so that a first inventory runs as written (the InitSection's `values` otherwise: placeholders).

- flavor: the smallest public flavor a clone fits in (1 vCPU, 1.5 GB of RAM, 10 GB of disk or the
  image's size);
- external_network: the network floating IPs come from (`router:external`), `public` first when
  there are several;
- operator_cidr: this host's own address on its way to that network (or to Keystone), as a /32,
  when the cloud sees it as it is: an address of the external network's subnets, or a global one.
  Behind NAT (a private address) the cloud sees another address, which this host cannot know: the
  placeholder stays, and its comment says so."""

from __future__ import annotations

import ipaddress
import socket
from urllib.parse import urlparse

from ...errors import CcrpError, InputError
from . import errors

MIN_VCPUS, MIN_RAM_MB, MIN_DISK_GB = 1, 1536, 10


def _source_address(target: str) -> ipaddress.IPv4Address | None:
    """The address this host sends from towards `target` (a UDP socket's connect sends nothing)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect((target, 9))
            return ipaddress.IPv4Address(s.getsockname()[0])
    except (OSError, ValueError):
        return None


def pick_flavor(flavors: list) -> str | None:
    fits = [f for f in flavors if (f.vcpus or 0) >= MIN_VCPUS and (f.ram or 0) >= MIN_RAM_MB
            and ((f.disk or 0) == 0 or f.disk >= MIN_DISK_GB)]
    best = min(fits, key=lambda f: (f.ram, f.vcpus, f.disk or 0, f.name), default=None)
    return best.name if best else None


def operator_address(targets: list[str], own_ranges: list[ipaddress.IPv4Network]) -> ipaddress.IPv4Address | None:
    """This host's address towards the first target it has a route to, when the cloud sees that one."""
    for target in targets:
        source = _source_address(target)
        if source is None:
            continue
        if source.is_global or any(source in net for net in own_ranges):
            return source
        return None  # a private address: behind NAT, the cloud sees another
    return None


def init_values(cloud: str) -> dict[str, str]:
    from .client import _connect

    conn = _connect(cloud)
    try:
        flavors = list(conn.compute.flavors(is_public=True))
        externals = list(conn.network.networks(is_router_external=True))
        subnets = [s for n in externals for s in conn.network.subnets(network_id=n.id) if s.ip_version == 4]
    except Exception as exc:  # noqa: BLE001 - the SDK's errors, in one line
        if isinstance(exc, CcrpError) or not errors.is_sdk_error(exc):
            raise
        raise errors.to_ccrp(f"ccrp init --cloud {cloud}", cloud, exc) from None
    finally:
        conn.close()
    flavor = pick_flavor(flavors)
    if flavor is None:
        raise InputError(f"cloud {cloud!r} has no public flavor a clone fits in ({MIN_VCPUS} vCPU, {MIN_RAM_MB} MB, "
                         f"{MIN_DISK_GB} GB)", hint="ask the cloud's admin for one, or run init without --cloud")
    if not externals:
        raise InputError(f"cloud {cloud!r} has no external network (floating IPs come from one)",
                         hint="ask the cloud's admin for one, or run init without --cloud")
    external = next((n for n in externals if n.name == "public"), externals[0])
    ranges = [ipaddress.IPv4Network(s.cidr) for s in subnets]
    targets = [s.gateway_ip for s in subnets if s.gateway_ip] + [urlparse((conn.config.config.get("auth") or {}).get("auth_url", "")).hostname or ""]
    address = operator_address([t for t in targets if t], ranges)
    values = {"cloud": cloud, "flavor": flavor, "external_network": external.name}
    if address is not None:
        values |= {"operator_cidr": f"{address}/32",
                   "operator_note": f"this host, as {cloud} sees it (found by ccrp init --cloud)"}
    else:
        values["operator_note"] = "put your public address range (this host is behind NAT: ccrp cannot see it)"
    return values
