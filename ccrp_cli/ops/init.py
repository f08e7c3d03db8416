"""`ccrp init`: a first, commented ccrp.yaml whose address pools clash with nothing on this host."""

from __future__ import annotations

import ipaddress
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import InputError, cannot_write, shown
from ..store import ccrp_home

if TYPE_CHECKING:
    from ..providers.base import InitSection

# Where each pool is looked for, and the size of one: the lab's choices first.
SEARCH = {"public": ("172.30.0.0/15", 24), "common": ("10.90.0.0/16", 24), "vpn": ("10.80.0.0/12", 16)}
# A new fleet is ROS 2, on the current LTS (docs/ros2.md); `--distro noetic` for a ROS 1 fleet.
DEFAULT_DISTRO = "jazzy"


def host_ranges() -> dict[str, str]:
    """What a new network must not shadow on this host: its routes (not the default one), what the
    backends have taken here (ProviderInfo.host_networks: Docker's networks, libvirt's) and its DNS
    servers, range -> what it is."""
    from ..providers import REGISTRY, _load

    ranges: dict[str, str] = {}
    try:
        for line in Path("/proc/net/route").read_text().splitlines()[1:]:
            f = line.split()
            dest, mask = (ipaddress.IPv4Address(int(x, 16).to_bytes(4, "little")) for x in (f[1], f[7]))
            if int(mask):
                ranges[str(ipaddress.IPv4Network(f"{dest}/{mask}", strict=False))] = f"route via {f[0]}"
    except (OSError, ValueError, IndexError):
        pass
    for backend in REGISTRY.values():
        if backend.host_networks:
            ranges |= _load(backend.host_networks)()
    try:
        for line in Path("/etc/resolv.conf").read_text().splitlines():
            f = line.split()
            if len(f) >= 2 and f[0] == "nameserver" and ":" not in f[1]:
                ranges[f"{f[1]}/32"] = "DNS server"
    except OSError:
        pass
    return ranges


def used_networks() -> list[ipaddress.IPv4Network]:
    """What a new fleet's pools must not overlap: this host's routes, DNS servers and backends'
    networks, and the addresses of every fleet in $CCRP_HOME."""
    used = [ipaddress.IPv4Network(r) for r in host_ranges()]
    for state in ccrp_home().glob("*/state.json"):
        try:
            robots = json.loads(state.read_text()).get("robots", {})
        except (OSError, ValueError):
            continue
        for rec in robots.values():
            for key in ("common", "vpn"):
                ip = (rec.get("addresses") or {}).get(key)
                if ip:
                    used.append(ipaddress.IPv4Network(f"{ip}/{24 if key == 'common' else 16}", strict=False))
    return used


def free(kind: str, used: list[ipaddress.IPv4Network]) -> str:
    within, prefix = SEARCH[kind]
    for net in ipaddress.IPv4Network(within).subnets(new_prefix=prefix):
        if not any(net.overlaps(u) for u in used):
            used.append(net)
            return str(net)
    raise InputError(f"no free /{prefix} for the {kind} pool in {within} on this host", hint="write the pools by hand")


def offered() -> dict[str, InitSection]:
    """The backends `ccrp init` writes a first inventory for (ProviderInfo.init), in the registry's order."""
    from ..providers import REGISTRY

    return {kind: i.init for kind, i in REGISTRY.items() if i.init is not None}


def default_provider() -> str:
    """The backend `ccrp init` writes with no --provider (the one whose InitSection says so)."""
    return next(kind for kind, section in offered().items() if section.default)


def default_fleet() -> str:
    from ..models.names import NAME_RE

    name = Path.cwd().name.lower()
    return name if NAME_RE.fullmatch(name) else "lab"


def write(path: Path, provider: str, robots: list[str], fleet: str, distro: str = DEFAULT_DISTRO,
          cloud: str = "") -> dict[str, Any]:
    """Write the first inventory of `provider` (empty: init's default backend) to `path`; with
    `cloud`, the backend's values asked of that cloud (InitSection.discover)."""
    from ..models.names import check_name
    from ..recipes import distros
    from ..templates import render

    sections = offered()
    provider = provider or default_provider()
    if provider not in sections:
        raise InputError(f"--provider {shown(provider)}: choose from {', '.join(sections)}")
    section = sections[provider]
    if distro not in distros():
        raise InputError(f"--distro {shown(distro)}: choose from {', '.join(distros())}")
    check_name(fleet, "fleet name")
    for name in robots:
        check_name(name)
    if len(set(robots)) != len(robots) or not robots:
        raise InputError("--robots: one or more different names, comma-separated", hint="e.g. --robots nao1,nao2")
    if cloud and section.discover is None:
        raise InputError(f"--cloud is for --provider {', '.join(k for k, v in sections.items() if v.discover)}",
                         hint="the other backends' first inventory needs no cloud entry")
    if path.exists():
        raise InputError(f"{path} exists: ccrp init never overwrites an inventory", hint="edit it, or remove it first")
    values = dict(section.values)
    if cloud and section.discover is not None:  # refused above without one
        from ..providers import _load

        from ..models.values import check_cloud_name

        values |= _load(section.discover)(cloud)
        # Names the cloud chose reach the file: one token each, or nothing is written.
        for key, value in values.items():
            if key != "operator_note":
                try:
                    check_cloud_name(value)
                except ValueError as exc:
                    raise InputError(f"cloud {shown(cloud)} answered a {key} that ccrp will not write: {exc}") from None
    used = used_networks()
    pools = {"public": free("public", used) if section.public_pool else None,
             "common": free("common", used), "vpn_pool": free("vpn", used)}
    others = [d for d in distros() if d != distro]
    text = render("init/ccrp.yaml.j2", fleet=fleet, provider_lines=section.lines.format(public=pools["public"], **values),
                  autostop=section.autostop, robots=robots, distro=distro, ros2=distros()[distro] == 2, others=others,
                  **pools)
    with cannot_write(path):
        with open(path, "x") as fh:  # exclusive: a file made meanwhile is not overwritten either
            fh.write(text)
    found = {k: v for k, v in values.items() if k != "operator_note"} if cloud else {}
    return {"path": str(path), "fleet": fleet, "provider": provider, "distro": distro, "robots": robots, **pools, **found}
