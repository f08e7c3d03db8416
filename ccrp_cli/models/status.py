"""A robot's row of `ccrp status`: what `status --json` prints, what alerts are made from, what the
dashboard's page gets (a whitelist of its fields, dashboard/events.py) and what its JavaScript
reads. One type for all of them, so a field renamed or added is renamed or added everywhere.

The parts read from a clone (its health report, its power device's report, its nodes) are
validated here: a clone is a machine a user can log in to, and what it reports is data, not code.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict

from .software import Ready


class _Part(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Watchdog(_Part):
    """The robot's watchdog (docs/dashboard.md): read in a simulated robot's container, inferred
    from the clone's side for a real robot, or `off` when its power device says so."""

    state: Literal["connected", "brainless", "starting", "off", "unknown"]
    since: str | None = None  # ISO time of the last change, where known
    source: Literal["simulated robot", "clone", "power device"]
    motors: str | None = None  # the simulated robot's stand-in motors (its fallback hook's)


class Power(_Part):
    """The power device's last report on the clone (docs/dashboard.md). All None: a simulated
    robot whose device has not started yet (its power is on)."""

    relay: Literal["on", "off"] | None = None
    robot: Literal["running", "off", "starting"] | None = None
    reported_at: str | None = None  # the clone's time when the report arrived
    age_s: float | None = None
    silent: bool = False


class Node(_Part):
    """One of the robot's own nodes on its clone (docs/workloads.md), as systemd sees it."""

    name: str
    state: str  # systemd's ActiveState: active, failed, activating...
    sub: str = ""
    restarts: int | None = None
    digest: str | None = None  # of what it runs: the software of the snapshot or of a deploy
    ready_check: Ready | None = None  # its `ready` as the clone keeps it
    # `ccrp status --ready` only (None: not checked): whether it is ready now, and why not.
    ready: bool | None = None
    not_ready: str | None = None


class ApiManager(_Part):
    """The robot's API manager (docs/services.md); `running` only while its agent reports."""

    running: bool
    backend: str
    calls: int = 0
    errors: int = 0
    published: int = 0
    last_latency_ms: float | None = None
    last_error: str | None = None


class Knowledge(_Part):
    """The clone's knowledge agent (docs/services.md); `running` only while it reports."""

    running: bool
    datasets: dict[str, dict] = {}  # dataset -> the agent's counts (items, bytes)
    peers: dict[str, bool] = {}
    errors: int = 0
    last_error: str | None = None
    last_reconcile: float | None = None  # the agent's clock


class StatusRow(BaseModel):
    """One robot, its clone and what runs between them."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    robot: str
    clone: str  # the clone's host name
    phase: str  # ccrp's record of it (state.json); `planned` before the first fleet up
    status: str  # the provider's word, with `(idle)` or `(unreachable)` where that explains it
    state: str  # ccrp's word for it, the same on every provider; `absent` when there is none
    public_ip: str | None = None  # the clone's own (none behind an entry gateway)
    vpn_endpoint: str | None = None  # HOST:PORT the robot's bundle dials: its clone, or its port on the gateway
    common_ip: str
    vpn_subnet: str
    vpn_connected: bool = False
    secrets: bool | None = None  # whether the clone holds its keys (a rebooted cloud clone lost them)
    robot_address: str | None = None  # the robot's real address, as its tunnel's server sees it
    robot_rtt_ms: float | None = None  # one ICMP echo from the clone to the robot through its tunnel
    # ROS 2 has no master: there it says whether the clone's graph answered.
    master_reachable: bool = False
    ros_distro: str
    robot_nodes: list[str] = []
    stale_nodes: list[str] = []  # registered on the master, while the robot has no session
    relay_running: bool = False
    relay_peers: dict[str, bool] = {}
    revoked_at: str | None = None
    autostop_idle_s: int | None = None
    stopped_idle: str | None = None  # the autostop agent's note, when it powered the clone off
    unreachable: str | None = None  # why the health check of a running clone failed
    software: str | None = None  # the software digest the clone runs, as ccrp recorded it
    # The last `ccrp deploy`'s software, which this clone (not running) gets when it starts.
    software_pending: str | None = None
    api_manager: ApiManager | None = None
    knowledge: Knowledge | None = None
    power: Power | None = None  # None: no device reported since the clone booted
    nodes: list[Node] | None = None  # None where the robot runs none of its own
    watchdog: Watchdog | None = None
    alerts: list[dict] | None = None  # `status --json` only: this robot's alerts and the fleet's

    def json_dict(self) -> dict:
        """As `status --json` prints it (without `alerts` unless they were attached)."""
        return self.model_dump(mode="json", exclude={"alerts"} if self.alerts is None else None)
