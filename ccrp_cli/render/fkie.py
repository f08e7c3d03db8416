"""The fkie engine (multimaster_fkie, as in the thesis): per clone, a launch file with
master_discovery in unicast mode and master_sync filtering on the receiving side, the exports
republished under the robot's namespace, and the hosts entries and routes that make synced
publishers reachable over the common network.

No command renders or pushes these: multimaster_fkie exists only for ROS 1 on Ubuntu 20.04
(packages.ros.org), every clone runs Debian 12, and inventories with `sharing.engine: fkie` are
refused (models/inventory.py). The renderer stays, tested against roslaunch's own parser
(tests/unit/test_sharing.py), as the record of the thesis's sharing set-up (docs/sharing.md).
"""

from __future__ import annotations

from ..fleet import Fleet
from ..models.names import clone_host
from ..models.state import FleetState
from ..sharing import routes
from .templates import render


def launch(fleet: Fleet, state: FleetState, robot: str) -> str:
    members = fleet.members(state)
    plan = fleet.plan(state)
    mine = [r for r in routes(members) if r.dest == robot]
    sync: dict[str, list[str]] = {}
    for r in mine:
        sync.setdefault(clone_host(r.source), []).append(r.local_name)
    exported = sorted({r.topic for r in routes(members) if r.source == robot})
    return render(
        "fkie/sharing.launch.j2", fleet=fleet.name, clone_host=clone_host(robot),
        robot_hosts=[clone_host(n) for n in plan if n != robot], sync_hosts=sorted(sync),
        sync_topics={h: sorted(t) for h, t in sorted(sync.items())},
        exports=[(t, f"/{robot}{t}") for t in exported],
    )


def network(fleet: Fleet, state: FleetState, robot: str) -> tuple[str, list[list[str]]]:
    """(hosts lines, `ip route` argv lists) for robot's clone: every other clone by name, the other
    robots by their VPN address, and a route to each other clone's VPN subnet via that clone."""
    plan = fleet.plan(state)
    hosts, cmds = [], []
    for name, a in plan.items():
        if name == robot:
            continue
        hosts += [f"{a.common_ip} {a.clone_host}", f"{a.robot_vpn_ip} {name}"]
        cmds.append(["ip", "route", "replace", str(a.vpn_subnet), "via", str(a.common_ip)])
    return "\n".join(hosts) + "\n", cmds
