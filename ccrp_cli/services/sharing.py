"""Topic sharing between clones: the effective policy and what each clone's engine needs.

A route is (source robot, topic, destination robot): the source's clone exports `topic`, the
destination's clone imports it and sees it as /<source><topic>, so two robots' identical topic
names never collide. Each clone's relay config is rendered from these routes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

from ..fleet import Fleet
from ..models.layout import CCRP_ETC, CCRP_LIB, RELAY_USER
from ..models.inventory import Robot
from ..models.state import FleetState
from ..render.files import BundleFile
from .base import Boot, CloneService, ServiceContext


@dataclass(frozen=True, order=True)
class Route:
    source: str
    topic: str
    dest: str

    @property
    def local_name(self) -> str:
        """The topic's name on the destination clone."""
        return f"/{self.source}{self.topic}"


def routes(members: list[Robot]) -> list[Route]:
    """Every (source, topic, destination) the policy allows; imports of robots not (or no longer)
    in the fleet are dropped, and so are imports the source does not export."""
    exports = {r.name: set(r.exports) for r in members}
    out = [
        Route(source, topic, r.name)
        for r in members
        for source, topics in r.imports.items()
        for topic in topics
        if source != r.name and topic in exports.get(source, ())
    ]
    return sorted(set(out))


def key_expr(fleet: str, source: str, topic: str) -> str:
    """Zenoh key of a topic exported by `source`: ccrp/<fleet>/<source>/<topic path>."""
    return f"ccrp/{fleet}/{source}/{topic.strip('/')}"


def zenoh_id(fleet: str, robot: str) -> str:
    """The stable part of a clone agent's Zenoh id (24 hex digits), so `ccrp status` can name the
    peers an agent sees. Each session the agent opens adds 8 random ones (agent/relay.py
    session_id): a session opened again for a new peer list is a new peer to the others, never
    taken for the one it replaces while that one's links are still being torn down."""
    return "c" + hashlib.sha256(f"{fleet}/{robot}".encode()).hexdigest()[:23]


def relay_config(fleet: Fleet, state: FleetState, robot: str, live: set[str] | None = None) -> dict:
    """/etc/ccrp/relay.json of robot's clone. Not secret: the TLS files it names come as secrets.
    `live`: the clones taken as up (by default those state calls ready)."""
    from ..models.layout import SECRETS_DIR

    inv = fleet.inventory
    plan = fleet.plan(state)
    # Only clones that are up take part: a deleted clone drops out of every other's config.
    if live is None:
        live = {n for n, rec in state.robots.items() if rec.phase == "ready"}
    live = set(live) | {robot}
    members = [m for m in fleet.members(state) if m.name in plan and m.name in live]
    me = next(m for m in members if m.name == robot)
    port = inv.sharing.relay_port
    all_routes = routes(members)
    # Only clones that exchange something with this one are peers: fewer links, same result.
    partners = sorted({r.dest for r in all_routes if r.source == robot} | {r.source for r in all_routes if r.dest == robot})
    # A partner is admitted by the CN of its current relay certificate (the agent's Zenoh access
    # control): one without a valid certificate is left out until `fleet up` issues one.
    cns = fleet.pki.relay_cns()
    partners = [p for p in partners if p in cns]
    return {
        "fleet": inv.fleet,
        "robot": robot,
        "id": zenoh_id(inv.fleet, robot),
        "listen": f"tls/{plan[robot].common_ip}:{port}",
        "peers": {p: {"endpoint": f"tls/{plan[p].common_ip}:{port}", "id": zenoh_id(inv.fleet, p), "cn": cns[p]}
                  for p in partners},
        "exports": sorted(t for t in me.exports if any(r.source == robot and r.topic == t for r in all_routes)),
        "imports": [asdict(r) | {"as": r.local_name} for r in all_routes if r.dest == robot],
        "tls": {"ca": f"{SECRETS_DIR}/relay-ca.crt", "cert": f"{SECRETS_DIR}/relay.crt", "key": f"{SECRETS_DIR}/relay.key"},
        "status": "/run/ccrp-relay/status.json",
        "config": f"{CCRP_ETC}/relay.json",
    }


def relay_config_text(fleet: Fleet, state: FleetState, robot: str, live: set[str] | None = None) -> str:
    return json.dumps(relay_config(fleet, state, robot, live), indent=1, sort_keys=True) + "\n"


def relay_config_file(fleet: Fleet, state: FleetState, robot: str, live: set[str] | None = None) -> BundleFile:
    return BundleFile("relay.json", relay_config_text(fleet, state, robot, live), 0o644, f"{CCRP_ETC}/relay.json")


def relay_link(h: dict, expected: list[str]) -> tuple[bool, dict[str, bool]]:
    """From a clone's health: whether its relay agent runs, and its peers (name -> connected). The
    agent's own report counts only while it runs (health.py: a status file under 10 s old); the
    last report of a stopped agent would show sharing that no longer happens, so then every peer
    ccrp configured (`expected`) is down."""
    relay = h.get("relay") or {}
    if relay.get("running"):
        return True, dict(relay.get("peers") or {})
    return False, dict.fromkeys(sorted(expected), False)


class Relay(CloneService):
    """The topic relay (agent/relay.py): its unit comes with the user-data, its agent with the
    snapshot (or the user-data: ROS 2, a bare image); `fleet up` pushes relay.json, which the agent
    re-reads within a second, and its TLS files with the keys (which restart it)."""

    name = "relay"
    settings = True
    reshared = True
    # In every ROS 1 snapshot, and in a bare clone's user-data: `fleet up` pushes only its config. A
    # ROS 2 image has no agents of ccrp (the wheels' venv alone): the relay's come with the user-data.
    boot = Boot(units=("ccrp-relay.service",), image_agents=("relay",), bare_agents=("relay",),
                ros2_agents=("relay", "relay_ros2"), users=(RELAY_USER,))

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        files = [relay_config_file(ctx.fleet, ctx.state, ctx.robot.name, ctx.live)]
        if ctx.fleet.inventory.ros.ros2:
            # The loader of the workspace's message types (ROS 2 interface packages): pushed as the
            # knowledge agent is, since a bare AWS clone's user-data had no room left for it (and a
            # bare clone has no workspace). relay_ros2.py imports it when a type is not the distro's.
            from ..resources import agent_source

            files.append(BundleFile("relay_interfaces.py", agent_source("relay_interfaces"), 0o644,
                                    f"{CCRP_LIB}/relay_interfaces.py"))
        return files

    def status(self, fleet: Fleet, state: FleetState, robot: Robot, health: dict | None) -> dict:
        if health is None:
            return {}
        running, peers = relay_link(health, list(relay_config(fleet, state, robot.name)["peers"]))
        return {"relay_running": running, "relay_peers": peers}


def matrix(fleet: Fleet, state: FleetState) -> list[dict]:
    """`ccrp topics`: who exports what to whom, as rows."""
    members = fleet.members(state)
    rows: list[dict[str, str | None]] = [{"source": r.source, "topic": r.topic, "dest": r.dest, "as": r.local_name}
                                         for r in routes(members)]
    exported = {(r["source"], r["topic"]) for r in rows}
    # Exports nobody imports yet: shown so the operator sees what is offered.
    rows += [{"source": m.name, "topic": t, "dest": None, "as": None}
             for m in members for t in m.exports if (m.name, t) not in exported]
    return sorted(rows, key=lambda r: (r["source"], r["topic"], r["dest"] or ""))
