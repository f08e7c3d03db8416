"""The entry gateway of a cloud fleet (docs/architecture.md "Entry gateway"): one small instance
holds the fleet's one public address, and each robot dials its own port on it, forwarded to its
clone's VPN port on the common network. The clones have no public address.

The gateway is cattle: everything it does is in two files rendered from the inventory and the
address plan (its firewall and forwarding rules, and the unit that loads them), so re-creating it
from the state gives the same gateway. It never holds a key or a password: the tunnels stay end to
end between robot and clone, and the gateway sees only their encrypted packets."""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from ..models.addressing import CloneAddresses, entry_port, gateway_ip
from ..models.inventory import Inventory
from ..models.layout import CCRP_ETC
from ..templates import render, static
from .cloudinit import _file, dump, login_user

RULES_PATH = f"{CCRP_ETC}/gateway.rules"
UNIT = "ccrp-gateway.service"


@dataclass(frozen=True)
class Entry:
    """One robot's way in: `port` on the gateway, forwarded to its clone's VPN port."""

    robot: str
    port: int
    clone_ip: ipaddress.IPv4Address


def entries(inv: Inventory, plan: Iterable[CloneAddresses]) -> list[Entry]:
    """The robots' entries, by port (the address plan gives each robot its slot)."""
    return sorted((Entry(a.robot, entry_port(inv, a.index), a.common_ip) for a in plan), key=lambda e: e.port)


def rules(inv: Inventory, found: Sequence[Entry], operator_cidr: str) -> str:
    """The gateway's iptables-restore rules: nat (each robot's port, the clones' way out) and filter
    (only those ports forwarded, SSH only from `operator_cidr`)."""
    return render("gateway/gateway.rules.j2", fleet=inv.fleet, entries=found, operator_cidr=operator_cidr,
                  proto=inv.vpn.proto, vpn_port=inv.vpn.port, common_cidr=inv.common.cidr, gateway_ip=gateway_ip(inv))


def files(inv: Inventory, found: Sequence[Entry], operator_cidr: str) -> list[dict[str, Any]]:
    """What makes an instance the gateway, as cloud-config write_files entries."""
    return [_file(RULES_PATH, rules(inv, found, operator_cidr), "0600"),
            _file(f"/etc/systemd/system/{UNIT}", static(f"systemd/{UNIT}"))]


def user_data(inv: Inventory, found: Sequence[Entry], operator_cidr: str, login_keys: list[str]) -> str:
    """The gateway's cloud-config: the operator's login, the rules and their unit, enabled."""
    data: dict[str, Any] = {
        "users": [login_user(login_keys)],  # no "default": the images' own login users differ per cloud
        "write_files": files(inv, found, operator_cidr),
        "runcmd": [["systemctl", "daemon-reload"], ["systemctl", "enable", "--now", UNIT]],
    }
    return dump(data)
