"""ccrp status."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import typer

from . import options, output

if TYPE_CHECKING:
    from ..models.status import ApiManager, Knowledge, Node, StatusRow


def status(inventory: options.Inventory, as_json: options.Json = False,
           ready: Annotated[bool, typer.Option("--ready", help="check each running node's readiness now: one try of its "
                                                "`ready` check (a topic or a command; up to 15 s each)")] = False) -> None:
    """Per robot: clone state, addresses, VPN connected, master reachable, robot nodes on its master,
    the robot's watchdog (connected / brainless); then the fleet's alerts (clone down, robot
    brainless, certificate or CRL near expiry...), as the dashboard shows them."""
    from ..alerts import fleet_alerts
    from ..providers import get_provider
    from ..ops.status import fleet_status
    from ..robot.watchdog import cell as watchdog_cell
    from ..robot.watchdog import power_cell

    fleet = options.open_fleet(inventory)
    rows = fleet_status(fleet, get_provider(fleet.inventory), ready=ready)
    alerts = fleet_alerts(fleet, rows)
    for r in rows:  # --json: each row with its alerts and the fleet's own (CRL, CAs), which touch every robot
        r.alerts = [a for a in alerts if a["robot"] in (None, r.robot)]
    yes = lambda b: "yes" if b else "no"  # noqa: E731
    # The API manager's column only when some robot has one (docs/services.md).
    api = any(r.api_manager for r in rows)
    know = any(r.knowledge for r in rows)  # where services.knowledge shares a dataset
    power = any(r.power for r in rows)  # a power device ccrp reaches (simulated robots'): docs/dashboard.md
    own = any(r.nodes for r in rows)  # the robots' own software (docs/workloads.md)
    output.emit(
        [r.json_dict() for r in rows], as_json,
        # ROS 2 has no master: there the column says whether the clone's ROS 2 graph answered.
        ["ROBOT", "CLONE", "STATE", "VPN ENDPOINT", "COMMON IP", "VPN", "GRAPH" if fleet.inventory.ros.ros2 else "MASTER",
         "ROBOT NODES", "RELAY PEERS", "WATCHDOG"]
        + (["POWER"] if power else []) + (["API MANAGER"] if api else []) + (["KNOWLEDGE"] if know else [])
        + (["NODES"] if own else []),
        [(r.robot, r.clone, r.status, r.vpn_endpoint, r.common_ip,
          vpn_cell(r), yes(r.master_reachable),
          nodes_cell(r), relay_peers(r.relay_peers, r.relay_running), watchdog_cell(r.watchdog))
         + ((power_cell(r.power),) if power else ())
         + ((api_cell(r.api_manager),) if api else ())
         + ((knowledge_cell(r.knowledge),) if know else ())
         + ((own_nodes_cell(r.nodes),) if own else ()) for r in rows],
    )
    if alerts and not as_json:
        output.table(["LEVEL", "ROBOT", "ALERT"], [(a["level"], a["robot"] or "(fleet)", a["text"]) for a in alerts],
                     title=f"\n{len(alerts)} alert(s)")


def own_nodes_cell(nodes: list[Node] | None) -> str:
    """The robot's own nodes: `mapper active`, `mapper failed (4 restarts)`; with --ready,
    `mapper active ready`, `mapper active NOT READY (no message on /map ...)`."""
    def cell(n: Node) -> str:
        text = f"{n.name} {n.state}" + (f" ({n.restarts} restarts)" if n.restarts else "")
        if n.ready is None or n.state != "active":
            return text
        return f"{text} ready" if n.ready else f"{text} NOT READY ({n.not_ready})"

    return ", ".join(cell(n) for n in nodes or [])


def nodes_cell(row: StatusRow) -> str:
    if row.stale_nodes:
        return f"(stale, robot not connected: {', '.join(row.stale_nodes)})"
    return ", ".join(row.robot_nodes)


def vpn_cell(row: StatusRow) -> str:
    revoked = row.revoked_at
    if row.vpn_connected:
        rtt = f", rtt {row.robot_rtt_ms:.1f} ms" if row.robot_rtt_ms is not None else ""
        return f"connected {row.robot_address}{rtt}" + (" (REVOKED: ending; if it stays, run vpn revoke again)" if revoked else "")
    if revoked:
        return f"revoked {revoked[:10]}"
    # A rebooted cloud clone: its keys lived in memory (docs/security.md).
    return "no (keys gone: run fleet up)" if row.secrets is False else "no"


def relay_peers(peers: dict[str, bool], running: bool = True) -> str:
    """"2/2" when every relay peer is connected; names the missing ones otherwise, and says so when
    the relay agent itself is not running (then nothing is shared)."""
    if not peers:
        return "-"
    down = sorted(p for p, up in peers.items() if not up)
    if not running:
        return f"0/{len(peers)} (relay not running)"
    return f"{len(peers) - len(down)}/{len(peers)}" + (f" (down: {', '.join(down)})" if down else "")


def knowledge_cell(k: Knowledge | None) -> str:
    """"faces 3, peers 2/2", or why the agent does not run."""
    if k is None:
        return "-"
    if not k.running:
        return "not running"
    sets = ", ".join(f"{ds} {d.get('items')}" for ds, d in sorted(k.datasets.items()))
    up = sum(k.peers.values())
    down = sorted(p for p, ok in k.peers.items() if not ok)
    return f"{sets}, peers {up}/{len(k.peers)}" + (f" (down: {', '.join(down)})" if down else "")


def api_cell(api: ApiManager | None) -> str:
    """"opencv: 12 calls, 0 errors, last 38.9 ms", or why it does not run."""
    if api is None:
        return "-"
    if not api.running:
        return f"{api.backend}: not running"
    last = f", last {api.last_latency_ms} ms" if api.last_latency_ms is not None else ""
    return f"{api.backend}: {api.calls} calls, {api.errors} errors{last}"
