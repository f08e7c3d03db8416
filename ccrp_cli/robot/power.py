"""Robot power (`ccrp robot power`, the dashboard's Power buttons): a power device on the robot's
power line, apart from the robot's computer, that switches it and reports its state every 3 s (the
thesis's Wake-on-LAN prototype: a relay driven by a small device).

The device has a VPN client of its own to the robot's clone (CN <robot>.power, its own password and
address; `ccrp robot power bundle` writes what it installs), so it reaches the clone while the
robot's computer, and with it the robot's tunnel, is off. On the clone the power agent
(agent/power.py) keeps the device's last report and answers each one with the state ccrp asked
for. ccrp asks by writing that state on the clone, and waits for a report that shows the robot off
or running. The same path serves a real device and a simulated robot's: `ccrp robot power` starts
a simulated device (a container of its own beside the simulated robot, with the device bundle
installed) the first time it is used on a simulated robot.
"""

from __future__ import annotations

import datetime as dt
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from ..errors import CcrpError, InputError, cannot_write
from ..fleet import Fleet, clone_view
from ..services.power import REPORT_S, parse_report

if TYPE_CHECKING:
    from ..providers.base import Lifecycle, Reaches

Say = Callable[[str], None]
WANT = "/run/ccrp-power/want"  # on the clone: what ccrp asks (agent/power.py reads it), in memory
REPORT = "/run/ccrp-power/report"  # on the clone: the device's last report (agent/power.py writes it)
ACTIONS = ("on", "off", "status", "bundle")
# Writes a state file atomically and prints the clone's clock then (reports carry the clone's
# time): a constant script, the path and state as arguments. It runs as root in /run/ccrp-power,
# which the agent's user owns: a link that user plants must not redirect root's write. So the
# temporary file is new and root's own (mkstemp: a random name, O_CREAT|O_EXCL|O_NOFOLLOW, so a
# link under that name fails the open instead of being followed), 0644 for the agent to read,
# and the rename replaces whatever is at the path (a link too) without following it. -I: root's
# Python imports nothing from the working directory or the environment.
SET_STATE = ["/usr/bin/python3", "-I", "-c", """
import os, sys, tempfile, time
path, state = sys.argv[1:]
os.makedirs(os.path.dirname(path), exist_ok=True)
fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), prefix=os.path.basename(path) + ".")
os.fchmod(fd, 0o644)
os.write(fd, (state + "\\n").encode())
os.close(fd)
os.replace(tmp, path)
print(int(time.time()))
"""]


def read(provider: Reaches, robot: str) -> dict | None:
    """The device's last report on the robot's clone, or None (it never reported since the clone
    booted)."""
    rc, out = provider.transport.exec(robot, ["cat", REPORT], timeout=15)
    return parse_report(out.strip().splitlines()[-1]) if rc == 0 and out.strip() else None


def device_files(fleet: Fleet, robot: str, remote: str | None = None) -> tuple[list, str]:
    """The power device's bundle (its certificate and password issued on first use) and the
    endpoint it dials: its robot's clone."""
    from ..render import bundles
    from .robots import endpoint_of

    with fleet.store.lock():
        state = fleet.store.load_state()
        fleet.robot(state, robot)
        endpoint = endpoint_of(fleet, state, robot, remote)
        vpn = fleet.inventory.vpn
        fleet.pki.issue_power(robot, vpn.cert_days, vpn.crl_days)
    view = clone_view(fleet, state, robot)
    return bundles.power_bundle(view, fleet.pki.credentials(robot), endpoint), endpoint


def push_passwd(fleet: Fleet, provider: Lifecycle, robot: str, say: Say) -> None:
    """The running clone gets who may connect now: its passwd file with the power device's name and
    password hash, or without them once the device is revoked. OpenVPN's checks read the file at
    every handshake: nothing restarts, the robot's session stays. A clone not running gets it with
    its other secrets when it is next brought up."""
    from ..render.files import applied_marker
    from ..probe import files_current
    from ..providers.base import CloneState
    from ..render import bundles

    rec = provider.query().get(robot)
    if rec is None or rec.state is not CloneState.RUNNING:
        say(f"{robot}: its clone is not running: `ccrp fleet up` gives it the power device's credentials")
        return
    view = clone_view(fleet, fleet.store.load_state(), robot)
    secrets = bundles.clone_secrets(view, fleet.pki.credentials(robot))
    keys = [f for f in secrets if f.name != "crl.pem"]
    passwd = next(f for f in keys if f.name == "passwd")
    # With the marker of what the clone holds, so that `fleet up` does not push (and restart)
    # again; unless another of its keys is not the current one: then `fleet up` pushes them all.
    others_current = files_current(provider, robot, [f for f in keys if f is not passwd])
    provider.transport.push_files(robot, [passwd, *([applied_marker(keys)] if others_current else [])], restart=[])


def write_device_bundle(fleet: Fleet, provider: Lifecycle, robot: str, out: Path, remote: str | None, say: Say) -> Path:
    """`ccrp robot power bundle`: the device's bundle in `out`, its name admitted by the clone."""
    from ..render import bundles

    files, endpoint = device_files(fleet, robot, remote)
    push_passwd(fleet, provider, robot, say)
    with cannot_write(out):
        return bundles.write_bundle(out, files, {"fleet": fleet.name, "robot": robot, "kind": "power-device",
                                                 "remote": endpoint})


def ensure_device(fleet: Fleet, provider: Lifecycle, robot: str, say: Say) -> tuple[dict, str]:
    """The device's last report and what the device is ("device", or "simulated" for the stand-in
    device of a simulated robot, (re)started here with a bundle of its own when it has not
    reported or went silent: it is ccrp's own, unlike a real one, which only `robot power bundle`
    issues credentials for)."""
    from ..retry import PollTimeout, poll
    from .simulated import Sims

    report = read(provider, robot)
    try:
        sims = Sims(fleet, provider)
        simulated = sims.running(robot)
    except CcrpError:  # no Docker engine here (a cloud fleet's operator machine): no simulated robots
        sims, simulated = None, False
    if simulated and (report is None or report["silent"]):
        say(f"{robot}: starting its simulated power device (a container beside the robot, with the device bundle)")
        files, _ = device_files(fleet, robot)
        push_passwd(fleet, provider, robot, say)
        sims.start_device(robot, files)
        try:
            report = poll(lambda: ((r := read(provider, robot)) is not None and not r["silent"], r), timeout=60, interval=0.5)
        except PollTimeout:
            raise CcrpError(f"the simulated power device of {robot!r} does not report to its clone: "
                            f"{sims.device_log(robot)[-300:]}") from None
    if report is None:
        raise InputError(f"robot {robot!r} has no power device reporting to its clone",
                         hint=f"ccrp robot power bundle --robot {robot}, installed on the device (docs/dashboard.md, Robot power)")
    return report, "simulated" if simulated else "device"


def end_dead_session(provider: Reaches, robot: str, say: Say) -> None:
    """A power cut gives OpenVPN no time to say goodbye: the clone would list the robot's session
    until its keepalive drops it (up to 2 minutes with the server's `keepalive 10 60`), and status
    would show a robot that is off as connected. The device's report says the robot is off: its
    session is dead, so it is ended on the clone now (as `vpn revoke` ends one)."""
    from ..probe import kill_session

    try:
        kill_session(provider, robot)
    except CcrpError as exc:  # the robot is off all the same; the keepalive will end the session
        say(f"{robot}: its clone still lists the dead VPN session until its keepalive drops it ({exc.message})")


def power(fleet: Fleet, robot: str, action: str, say: Say = lambda m: None, timeout: float = 30, provider: Lifecycle | None = None) -> dict:
    """Switch the robot's power on or off (or read it), and wait until the device reports it."""
    from ..providers import get_provider
    from ..retry import PollTimeout, poll

    if action not in ("on", "off", "status"):
        raise InputError(f"robot power {action[:20]!r}: choose on, off or status")
    fleet.robot(fleet.store.load_state(), robot)  # an unknown robot: bad input first
    provider = provider or get_provider(fleet.inventory)
    report, device = ensure_device(fleet, provider, robot, say)
    t0 = time.monotonic()
    if action != "status":
        rc, out = provider.transport.exec(robot, [*SET_STATE, WANT, action])
        asked = out.split()[-1] if out.split() else ""
        if rc != 0 or not asked.isdigit():
            raise CcrpError(f"cannot ask the power device of {robot!r} for {action} on its clone: {out.strip()[-200:]}")
        say(f"{robot}: relay {action} asked on its clone; waiting for the device's report (every {REPORT_S:g} s)")
        want = "off" if action == "off" else "running"

        def reported() -> tuple[bool, dict | None]:
            r = read(provider, robot)
            fresh = r is not None and dt.datetime.fromisoformat(r["reported_at"]).timestamp() >= int(asked)
            return bool(fresh and r["relay"] == action and r["robot"] == want), r

        try:
            report = poll(reported, timeout=timeout, interval=0.3)
        except PollTimeout as late:
            raise CcrpError(f"the power device of {robot!r} did not report the robot {want} within {timeout:g} s "
                            f"(last report: {late.last})") from None
        if action == "off":
            end_dead_session(provider, robot, say)
    return {"robot": robot, "power": report["relay"], "robot_state": report["robot"],
            "reported_at": report["reported_at"], "age_s": report["age_s"], "silent": report["silent"],
            "seconds": round(time.monotonic() - t0, 2), "device": device}
