"""`ccrp status`: per robot, the clone's state, addresses, VPN, master and the robot's nodes."""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

from ..services.registry import SERVICES
from ..services.workloads import ready_now, snapshot_software
from . import install_space
from ..errors import CcrpError
from ..fleet import Fleet
from ..models.status import Node, StatusRow
from ..probe import health, robot_link
from ..providers.base import CloneState

if TYPE_CHECKING:
    from ..models.inventory import Robot
    from ..models.state import FleetState
    from ..providers.base import Provider


def service_fields(fleet: Fleet, state: FleetState, robot: Robot, h: dict[str, Any] | None) -> dict[str, Any]:
    """The fields of robot's row that its clone services give (services/registry.py), from the clone's
    health report (None: the clone was not asked)."""
    return {k: v for service in SERVICES for k, v in service.status(fleet, state, robot, h).items()}


def checked_nodes(provider: Provider, robot: str, nodes: list[Node]) -> list[Node]:
    """`status --ready`: each node's readiness now. A node with a `ready` check is ready when one try
    of it passes (ready_now: a message on its topic, its command exiting 0); one without, when
    systemd has it active (its check at start was staying up)."""
    def one(node: Node) -> Node:
        if node.state != "active":
            why = f"is {node.state}"
        elif node.ready_check is None:
            why = None
        else:
            why = ready_now(provider, robot, node.ready_check)
        return node.model_copy(update={"ready": why is None, "not_ready": why})

    return [one(n) for n in nodes]


def fleet_status(fleet: Fleet, provider: Provider, ready: bool = False) -> list[StatusRow]:
    """Every robot's row; `ready`: each running clone's nodes are checked now (checked_nodes)."""
    state = fleet.store.load_state()
    actual = provider.query()
    plan = fleet.plan(state)

    index = fleet.pki.load_index() if fleet.pki.exists() else None
    revoked = {r: fleet.pki.revoked_since(r, index) for r in plan} if index else {}

    @functools.cache
    def pending() -> str | None:
        """The inventory's software when `ccrp deploy` kept it (a clone not running gets it when it
        starts), else None. Read (the workspace hashed) only when a stopped clone runs other
        software than the last deploy's: the inventory may have moved on, or back, since."""
        try:
            want = snapshot_software(fleet.inventory, fleet.path).digest
        except CcrpError:  # the inventory's software does not read: `fleet plan` says why
            return None
        return want if install_space.saved(fleet, want) is not None else None

    def one(robot: str) -> StatusRow:
        rec = actual.get(robot)
        a = plan[robot]
        member = fleet.robot(state, robot)
        ran = state.robots.get(robot)
        row = StatusRow(
            robot=robot,
            clone=a.clone_host,
            phase=state.robots[robot].phase if robot in state.robots else "planned",
            status=rec.status if rec else "absent",
            state=rec.state.value if rec else "absent",
            public_ip=rec.public_ip if rec else None,
            vpn_endpoint=state.robots[robot].public_endpoint if robot in state.robots else None,
            common_ip=str(a.common_ip),
            vpn_subnet=str(a.vpn_subnet),
            ros_distro=fleet.inventory.ros.distro,
            revoked_at=when.isoformat() if (when := revoked.get(robot)) else None,
            software=ran.software if ran else None,
            **service_fields(fleet, state, member, None),
        )
        if rec and rec.state is CloneState.STOPPED:
            note = provider.stop_note(robot)
            if note:  # its robot stayed away: the clone's autostop agent powered it off
                row.status, row.stopped_idle = "stopped (idle)", note
        if rec and rec.state is not CloneState.RUNNING and ran and state.deployed and ran.software != state.deployed \
                and pending() == state.deployed:
            row.software_pending = state.deployed  # ensure_clone gives it at the start
            row.status = f"{row.status} (deploy pending)"
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
                    **service_fields(fleet, state, member, h),
                }
                row = StatusRow.model_validate(row.model_dump() | update)
                if ready and row.nodes:
                    row.nodes = checked_nodes(provider, robot, row.nodes)
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
    from ..robot import watchdog

    with ThreadPoolExecutor(max_workers=min(provider.max_parallel, len(robots)) + 1) as pool:
        sims = pool.submit(watchdog.simulated, fleet, provider)
        rows = list(pool.map(one, robots))
        seen = sims.result()
    for row in rows:
        watchdog.join(row, seen.get(row.robot))
    return rows
