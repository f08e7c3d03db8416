"""`ccrp status`: per robot, the clone's state, addresses, VPN, master and the robot's nodes."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from urllib.parse import urlparse

from .clones import health
from .fleet import Fleet


def fleet_status(fleet: Fleet, provider) -> list[dict]:
    state = fleet.store.load_state()
    actual = provider.query()
    plan = fleet.plan(state)

    def one(robot: str) -> dict:
        rec = actual.get(robot)
        a = plan[robot]
        row = {
            "robot": robot,
            "clone": a.clone_host,
            "phase": state.robots[robot].phase if robot in state.robots else "planned",
            "status": rec.status if rec else "absent",
            "public_ip": rec.public_ip if rec else None,
            "common_ip": str(a.common_ip),
            "vpn_subnet": str(a.vpn_subnet),
            "vpn_connected": False,
            "robot_address": None,
            "master_reachable": False,
            "robot_nodes": [],
        }
        if rec and rec.status == "running":
            h = health(provider, robot)
            client = next((c for c in h["vpn"]["clients"] if c["cn"] == robot), None)
            row["vpn_connected"] = client is not None
            row["robot_address"] = client["real_address"] if client else None
            row["master_reachable"] = h["master"]["reachable"]
            # A robot node advertises an XML-RPC URI on the robot's own hostname.
            row["robot_nodes"] = sorted(n for n, uri in h["master"]["nodes"].items() if urlparse(uri).hostname == robot)
        return row

    robots = list(plan)
    if not robots:
        return []
    with ThreadPoolExecutor(max_workers=min(8, len(robots))) as pool:
        return list(pool.map(one, robots))
