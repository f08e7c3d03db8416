"""`ccrp status`: per robot, the clone's state, addresses, VPN, master and the robot's nodes."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

from .api_manager import api_manager_row
from .knowledge import knowledge_row
from .errors import CcrpError
from .fleet import Fleet
from .sharing import relay_config
from .power import parse_report
from .models.status import StatusRow
from .probe import health, robot_link
from .providers.base import CloneState

if TYPE_CHECKING:
    from .providers.base import Provider


def relay_link(h: dict, expected: list[str]) -> tuple[bool, dict[str, bool]]:
    """From a clone's health: whether its relay agent runs, and its peers (name -> connected). The
    agent's own report counts only while it runs (health.py: a status file under 10 s old); the
    last report of a stopped agent would show sharing that no longer happens, so then every peer
    ccrp configured (`expected`) is down."""
    relay = h.get("relay") or {}
    if relay.get("running"):
        return True, dict(relay.get("peers") or {})
    return False, dict.fromkeys(sorted(expected), False)


def fleet_status(fleet: Fleet, provider: Provider) -> list[StatusRow]:
    state = fleet.store.load_state()
    actual = provider.query()
    plan = fleet.plan(state)

    index = fleet.pki.load_index() if fleet.pki.exists() else None
    revoked = {r: fleet.pki.revoked_since(r, index) for r in plan} if index else {}

    def one(robot: str) -> StatusRow:
        rec = actual.get(robot)
        a = plan[robot]
        row = StatusRow(
            robot=robot,
            clone=a.clone_host,
            phase=state.robots[robot].phase if robot in state.robots else "planned",
            status=rec.status if rec else "absent",
            state=rec.state.value if rec else "absent",
            public_ip=rec.public_ip if rec else None,
            common_ip=str(a.common_ip),
            vpn_subnet=str(a.vpn_subnet),
            ros_distro=fleet.inventory.ros.distro,
            revoked_at=revoked[robot].isoformat() if revoked.get(robot) else None,
            autostop_idle_s=fleet.inventory.idle_of(fleet.robot(state, robot)) or None,
            api_manager=api_manager_row(fleet.inventory, fleet.robot(state, robot), None),
            knowledge=knowledge_row(fleet, state, robot, None),
        )
        if rec and rec.state is CloneState.STOPPED:
            note = provider.stop_note(robot)
            if note:  # its robot stayed away: the clone's autostop agent powered it off
                row.status, row.stopped_idle = "stopped (idle)", note
        if rec and rec.state is CloneState.RUNNING:
            try:
                h = health(provider, robot)
                client, nodes = robot_link(h, robot)
                # The master keeps a node registered after its robot's session ended: without the
                # session, it is a name on the master, not a robot that answers.
                update = {
                    "vpn_connected": client is not None,
                    "robot_nodes": nodes if client else [], "stale_nodes": [] if client else nodes,
                    "secrets": h.get("secrets"),
                    "robot_address": client["real_address"] if client else None,
                    "robot_rtt_ms": client.get("rtt_ms") if client else None,
                    "master_reachable": h["master"]["reachable"],
                    "api_manager": api_manager_row(fleet.inventory, fleet.robot(state, robot), h),
                    "knowledge": knowledge_row(fleet, state, robot, h),
                    "power": parse_report(h.get("power") or ""),  # None: no device reported since the clone booted
                    "nodes": h.get("nodes") or None,
                }
                update["relay_running"], update["relay_peers"] = relay_link(h, list(relay_config(fleet, state, robot)["peers"]))
                row = StatusRow.model_validate(row.model_dump() | update)
            except (CcrpError, KeyError, TypeError, ValueError) as exc:  # pydantic's ValidationError is a ValueError
                # Running to the cloud but not answering (booting, or shutting down: autostop, a
                # poweroff), or answering with a report that is not one. One such clone must not
                # hide the others' status.
                why = exc.one_line() if isinstance(exc, CcrpError) else f"its health report is malformed ({type(exc).__name__})"
                row.status, row.unreachable = f"{rec.status} (unreachable)", why
        return row

    robots = list(plan)
    if not robots:
        return []
    from . import watchdog

    with ThreadPoolExecutor(max_workers=min(provider.max_parallel, len(robots)) + 1) as pool:
        sims = pool.submit(watchdog.simulated, fleet, provider)
        rows = list(pool.map(one, robots))
        seen = sims.result()
    for row in rows:
        watchdog.join(row, seen.get(row.robot))
    return rows
