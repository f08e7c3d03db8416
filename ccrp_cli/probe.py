"""What a clone holds and reports, read through the provider's exec (any backend): its health
(agent/health.py run there), the digests of the files ccrp pushed, whether its robot is connected.
The clone pipeline (clones.py), its services and the status views all read clones this way; it
imports none of them."""

from __future__ import annotations

import hashlib
import json
import time
from urllib.parse import urlparse

from .errors import CcrpError
from .models.names import clone_host
from .providers.base import Reaches
from .resources import agent_source
from .retry import PollTimeout, poll


def HEALTH_SCRIPT() -> str:  # noqa: N802 - read like the constant it stands for
    """agent/health.py, run on the clone with `python3 -c` (stdlib only)."""
    return agent_source("health")


def health(provider: Reaches, robot: str) -> dict:
    # The script's own waits (the ROS 2 graph's) stretch as the transport's does on an emulated CPU.
    scale = provider.timeout_scale(robot)
    rc, out = provider.transport.exec(robot, ["env", f"CCRP_TIME_SCALE={scale}", "python3", "-c", HEALTH_SCRIPT()],
                                      timeout=20)
    try:
        return json.loads(out.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"vpn": {"up": False, "clients": []}, "master": {"reachable": False, "nodes": {}}, "error": out[-200:]}


def remote_digests(provider: Reaches, robot: str, files: list) -> dict[str, str]:
    """path -> sha256 of those of `files` that the clone holds (a missing one is left out)."""
    _, out = provider.transport.exec(robot, ["sha256sum", *(f.dest for f in files)], timeout=20)
    return {line.split()[1]: line.split()[0] for line in out.splitlines() if len(line.split()) == 2}


def same(have: dict[str, str], files: list) -> bool:
    return all(have.get(f.dest) == hashlib.sha256(f.content.encode()).hexdigest() for f in files)


def files_current(provider: Reaches, robot: str, files: list) -> bool:
    """True when the clone already holds exactly these files: re-running `fleet up` then leaves
    OpenVPN (and the robot's live session) and the relay alone."""
    return same(remote_digests(provider, robot, files), files)


def robot_link(h: dict, robot: str) -> tuple[dict | None, list[str]]:
    """From a clone's health: the robot's VPN client entry (or None) and its nodes on the master."""
    client = next((c for c in h["vpn"]["clients"] if c["cn"] == robot), None)
    # A robot node advertises an XML-RPC URI on the robot's own hostname (ROS 2: agent/ros2_graph.py
    # places it). rmw names an endpoint seen before its node's name _NODE_NAME_UNKNOWN_: no node yet
    # (under load, run 43 of docs/benchmarks.md, `robot sim --wait` took one for the robot's).
    nodes = sorted(n for n, uri in h["master"]["nodes"].items()
                   if urlparse(uri).hostname == robot and "_NODE_NAME_UNKNOWN_" not in n)
    return client, nodes


def wait_connected(provider: Reaches, robot: str, timeout: float) -> dict:
    """Until the robot's VPN session is up and at least one of its nodes is on its clone's master."""
    def linked() -> tuple[bool, tuple]:
        client, nodes = robot_link(health(provider, robot), robot)
        return bool(client and nodes), (client, nodes)

    t0 = time.monotonic()
    try:
        client, nodes = poll(linked, timeout=timeout, interval=0.25)
    except PollTimeout:
        raise CcrpError(f"robot {robot!r} did not connect to its clone within {timeout:.0f} s",
                        hint=f"ccrp clone exec --robot {robot} -- journalctl -u ccrp-openvpn -n 50") from None
    return {"robot": robot, "seconds": round(time.monotonic() - t0, 2), "address": client["real_address"], "nodes": nodes}


def kill_session(provider: Reaches, robot: str, cn: str | None = None) -> None:
    """End a live VPN session on the robot's clone (management interface): the robot's, or that
    of `cn` (its power device's)."""
    rc, out = provider.transport.exec(robot, ["python3", "-c", HEALTH_SCRIPT(), "kill", cn or robot], timeout=20)
    if rc != 0:
        raise CcrpError(f"cannot end the VPN session on {clone_host(robot)}: {out.strip()[-200:]}")
