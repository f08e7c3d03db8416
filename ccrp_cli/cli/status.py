"""ccrp status."""

from __future__ import annotations

from . import options, output


def status(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Per robot: clone state, addresses, VPN connected, master reachable, robot nodes on its master."""
    from ..providers import get_provider
    from ..status import fleet_status

    fleet = options.open_fleet(inventory)
    rows = fleet_status(fleet, get_provider(fleet.inventory))
    yes = lambda b: "yes" if b else "no"  # noqa: E731
    output.emit(
        rows, as_json,
        ["ROBOT", "CLONE", "STATE", "PUBLIC IP", "COMMON IP", "VPN", "MASTER", "ROBOT NODES", "RELAY PEERS"],
        [(r["robot"], r["clone"], r["status"], r["public_ip"], r["common_ip"],
          vpn_cell(r), yes(r["master_reachable"]),
          ", ".join(r["robot_nodes"]), relay_peers(r["relay_peers"], r["relay_running"])) for r in rows],
    )


def vpn_cell(row: dict) -> str:
    revoked = row.get("revoked_at")
    if row["vpn_connected"]:
        return f"connected {row['robot_address']}" + (" (REVOKED: ending; if it stays, run vpn revoke again)" if revoked else "")
    if revoked:
        return f"revoked {revoked[:10]}"
    # A rebooted cloud clone: its keys lived in memory (docs/security.md).
    return "no (keys gone: run fleet up)" if row["secrets"] is False else "no"


def relay_peers(peers: dict[str, bool], running: bool = True) -> str:
    """"2/2" when every relay peer is connected; names the missing ones otherwise, and says so when
    the relay agent itself is not running (then nothing is shared)."""
    if not peers:
        return "-"
    down = sorted(p for p, up in peers.items() if not up)
    if not running:
        return f"0/{len(peers)} (relay not running)"
    return f"{len(peers) - len(down)}/{len(peers)}" + (f" (down: {', '.join(down)})" if down else "")
