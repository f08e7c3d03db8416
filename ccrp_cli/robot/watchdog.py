"""The robot's watchdog as ccrp sees it: connected or brainless (templates/edge/ccrp-watchdog).

A simulated robot on this host is read in its container: the state its watchdog wrote (`ok|lost
<unix time>`) and the stand-in motors its fallback hook drives. A real robot has no way in but the
tunnel its watchdog watches, so its state is inferred from the clone's side: a VPN session and a
master that answers are exactly what the watchdog probes (connected); without a session the
robot is out of reach and what its watchdog decided is unknown until it comes back.
"""

from __future__ import annotations

import datetime as dt
import logging
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

from ..models.status import Power, StatusRow, Watchdog

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Provider

log = logging.getLogger("ccrp.watchdog")

STATE_FILE = "/run/ccrp/clone-state"  # CCRP_WATCHDOG_STATE's default, which the bundle keeps
MOTORS_FILE = "/run/ccrp/sim/motors"  # templates/sim/ccrp-sim-fallback
# One exec reads the files; a missing one reads as an empty line. A constant: no name reaches the shell.
READ = ["/bin/sh", "-c", 'for f in "$@"; do printf "%s " "$f"; head -n1 "$f" 2>/dev/null || echo; done',
        "ccrp-watchdog-state", STATE_FILE, MOTORS_FILE]
STATES = {"ok": "connected", "lost": "brainless"}


def _when(text: str) -> str | None:
    try:
        return dt.datetime.fromtimestamp(float(text), dt.timezone.utc).isoformat(timespec="seconds")
    except (ValueError, OverflowError, OSError):
        return None


def _files(out: str) -> dict[str, str]:
    files = {}
    for line in out.splitlines():
        path, _, rest = line.partition(" ")
        files[path] = rest.strip()
    return files


# The power column of a simulated robot whose device has not started yet (the first `ccrp robot
# power` starts it): its power is on.
NO_DEVICE_YET = Power()


def parse(out: str) -> Watchdog:
    """The READ command's output, as the robot's watchdog."""
    files = {path: rest.split() for path, rest in _files(out).items()}
    state, motors = files.get(STATE_FILE) or [], files.get(MOTORS_FILE) or []
    word = STATES.get(state[0]) if state else None
    return Watchdog(state=word or "starting",  # no file yet: the watchdog has not decided (first seconds)
                    since=_when(state[1]) if word and len(state) > 1 else None,
                    source="simulated robot",
                    motors=motors[0] if motors else "enabled")  # the hook has never run: as the robot started


def simulated(fleet: Fleet, provider: Provider) -> dict[str, Watchdog]:
    """robot -> its watchdog's state, for the fleet's simulated robots running on this host."""
    from .simulated import Sims

    try:
        sims = Sims(fleet, provider)
        robots = sims.names(running=True)
    except Exception as exc:  # noqa: BLE001 - no Docker here (a cloud fleet's host): no simulated robots
        log.debug("no simulated robots read: %s", exc)
        return {}

    def one(robot: str) -> tuple[str, Watchdog | None]:
        try:
            rc, out = sims.exec(robot, READ, timeout=10)
        except Exception as exc:  # noqa: BLE001 - removed meanwhile: no state, the others still count
            log.debug("watchdog state of %s not read: %s", robot, exc)
            return robot, None
        if rc != 0:
            return robot, None
        return robot, parse(out)

    if not robots:
        return {}
    with ThreadPoolExecutor(max_workers=min(8, len(robots))) as pool:
        return {r: s for r, s in pool.map(one, robots) if s is not None}


def join(row: StatusRow, sim: Watchdog | None) -> None:
    """A status row's watchdog and power columns, from its simulated robot's watchdog (`sim`, None
    for a robot not simulated here) and its power device's report on the clone (row.power)."""
    row.watchdog = sim or inferred(row)
    p = row.power
    if p is None and sim is not None:  # a simulated robot gets its device at the first `robot power`
        row.power = NO_DEVICE_YET
    elif p is not None and p.robot == "off":  # no watchdog runs on a robot powered off
        row.watchdog = Watchdog(state="off", since=p.reported_at, source="power device")


def inferred(row: StatusRow) -> Watchdog:
    """A robot without a simulated robot here: what its clone's side tells."""
    return Watchdog(state="connected" if row.vpn_connected and row.master_reachable else "unknown", source="clone")


def power_cell(p: Power | None) -> str:
    """`ccrp status`'s POWER column."""
    if not p:
        return "-"
    if p.relay is None:
        return "on (device not started)"
    text = p.relay if p.robot in ("running", "off") else f"{p.relay} (robot {p.robot})"
    return text + (f" (device silent for {p.age_s:.0f} s)" if p.silent else "")


def cell(w: Watchdog | None) -> str:
    """`ccrp status`'s WATCHDOG column."""
    if not w or w.state == "unknown":
        return "-"
    if w.state == "off":
        return "off (robot powered off)"
    text = w.state
    if w.since:
        text += f" since {w.since[11:19]}"
    if w.state == "brainless" and w.motors:
        text += f" (motors {w.motors})"
    return text + (" (seen from clone)" if w.source == "clone" else "")
