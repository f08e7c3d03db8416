"""Robot power (`ccrp robot power`, the dashboard's Power buttons): a power device on the robot's
power line, apart from the robot's computer, that switches it and reports its state every 3 s (the
thesis's Wake-on-LAN prototype: a relay driven by a small device).

Only simulated robots have one ccrp can reach: templates/sim/ccrp-power-agent, in the simulated
robot's container but not one of the robot's own units, with a stand-in device file for the relay
(docs/dashboard.md, "Robot power", says what a real device needs). ccrp writes the relay's new
state and waits for the device's report to show the robot off (its OpenVPN, watchdog and ROS node
stopped) or running again.
"""

from __future__ import annotations

import datetime as dt
import json
import time
from typing import Callable

from .errors import CcrpError, InputError
from .fleet import Fleet

Say = Callable[[str], None]
AGENT_PATH = "/usr/local/lib/ccrp/ccrp-power-agent"
UNIT = "ccrp-power-agent"
DEVICE = "/var/lib/ccrp/power/relay"
REPORT = "/run/ccrp/power/state"
REPORT_S = 3.0  # the device reports every 3 s; three missed reports make it silent
SILENT_S = 3 * REPORT_S
ACTIONS = ("on", "off", "status")
# Sets the relay: a constant script, the path and state as arguments.
SET_RELAY = ["/bin/sh", "-c", 'mkdir -p "${1%/*}" && printf "%s\\n" "$2" > "$1.tmp" && mv "$1.tmp" "$1"', "ccrp-power"]


def parse_report(text: str, now: float | None = None) -> dict | None:
    """The device's last report (one JSON line) -> {"relay", "robot", "reported_at", "age_s"}."""
    try:
        data = json.loads(text)
        t = float(data["t"])
        relay, robot = data["relay"], data["robot"]
    except (ValueError, KeyError, TypeError):
        return None
    if relay not in ("on", "off") or robot not in ("running", "off", "starting"):
        return None
    now = time.time() if now is None else now
    return {"relay": relay, "robot": robot, "age_s": round(max(0.0, now - t), 1),
            "reported_at": dt.datetime.fromtimestamp(t, dt.timezone.utc).isoformat(timespec="seconds")}


def _sims(fleet: Fleet, robot: str):
    from .simulated import Sims

    fleet.robot(fleet.store.load_state(), robot)  # an unknown robot: bad input first
    sims = Sims(fleet)
    if not sims.running(robot):
        raise InputError(f"robot {robot!r} has no power device ccrp can reach",
                         hint="only simulated robots have one (ccrp robot sim --robot R); docs/dashboard.md, Robot power")
    return sims


def read(sims, robot: str) -> dict | None:
    rc, out = sims.exec(robot, ["cat", REPORT], timeout=10)
    return parse_report(out.strip().splitlines()[-1]) if rc == 0 and out.strip() else None


def ensure_agent(sims, robot: str, say: Say) -> None:
    """The power agent runs in the simulated robot (installed on first use), and has reported."""
    from .render.bundles import BundleFile
    from .render.templates import static
    from .retry import PollTimeout, poll
    from .simulated import run_unit

    _, active = sims.exec(robot, ["systemctl", "is-active", UNIT])
    if active.strip() != "active":
        say(f"{robot}: starting its power device's agent ({UNIT})")
        sims.push(robot, [BundleFile("ccrp-power-agent", static("sim/ccrp-power-agent"), 0o755, AGENT_PATH)])
        run_unit(lambda argv: sims.exec(robot, argv), UNIT, ["/usr/bin/python3", AGENT_PATH],
                 f"simulated robot {robot!r}", ["--description", "ccrp power device (stand-in)",
                                                "--property", "Restart=always", "--property", "RestartSec=1"])
    try:
        poll(lambda: (read(sims, robot) is not None, None), timeout=10, interval=0.3)
    except PollTimeout:
        _, log = sims.exec(robot, ["journalctl", "-u", UNIT, "-n", "5", "--no-pager"])
        raise CcrpError(f"the power device of {robot!r} does not report: {log.strip()[-300:]}") from None


def power(fleet: Fleet, robot: str, action: str, say: Say = lambda m: None, timeout: float = 30) -> dict:
    """Switch the robot's power on or off (or read it), and wait until the device reports it."""
    from .retry import PollTimeout, poll

    if action not in ACTIONS:
        raise InputError(f"robot power {action[:20]!r}: choose on, off or status")
    sims = _sims(fleet, robot)
    ensure_agent(sims, robot, say)
    t0 = time.monotonic()
    if action != "status":
        asked = time.time()
        rc, out = sims.exec(robot, [*SET_RELAY, DEVICE, action])
        if rc != 0:
            raise CcrpError(f"cannot set the power relay of {robot!r}: {out.strip()[-200:]}")
        say(f"{robot}: relay {action}; waiting for the device's report (every {REPORT_S:g} s)")
        want = "off" if action == "off" else "running"

        def reported() -> tuple[bool, dict | None]:
            r = read(sims, robot)
            fresh = r is not None and dt.datetime.fromisoformat(r["reported_at"]).timestamp() >= int(asked)
            return bool(fresh and r["relay"] == action and r["robot"] == want), r

        try:
            report = poll(reported, timeout=timeout, interval=0.3)
        except PollTimeout as late:
            raise CcrpError(f"the power device of {robot!r} did not report the robot {want} within {timeout:g} s "
                            f"(last report: {late.last})") from None
    else:
        report = read(sims, robot)
    return {"robot": robot, "power": report["relay"], "robot_state": report["robot"],
            "reported_at": report["reported_at"], "seconds": round(time.monotonic() - t0, 2), "device": "simulated"}
