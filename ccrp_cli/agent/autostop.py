"""Autostop: powers this clone off when its robot has not been connected for the idle time ccrp
configured (/etc/ccrp/autostop.json, pushed by `ccrp fleet up`; idle 0 = never). Runs on the clone
as root (ccrp-autostop.service), so it works while the operator's machine is off. Stdlib only.

"Connected" is the robot's CN in OpenVPN's client list (its status file, rewritten every 10 s; an
older file means OpenVPN is not serving). The idle clock starts when this boot's OpenVPN first
serves (on a cloud, once ccrp pushed the keys that live in memory: a clone being started and
configured is not idle), at the robot's last connection, or when the setting changed, whichever
is latest. A clone whose OpenVPN never serves after a boot is of no use to its robot: it stops
after the idle time or UNCONFIGURED seconds from boot, whichever is longer.
"""

import json
import os
import subprocess
import sys
import time
from datetime import datetime, timezone

CONFIG = "/etc/ccrp/autostop.json"
STATUS = "/etc/openvpn/server/ccrp/status.log"
# Read by `ccrp status` from a stopped Docker clone's disk; the same line goes to the console,
# where a cloud keeps it after the instance stopped.
NOTE = "/var/lib/ccrp/autostop.note"
STATUS_FRESH = 30  # seconds: OpenVPN rewrites its status file every 10 s
UNCONFIGURED = 600


def read_config(path):
    try:
        with open(path) as f:
            cfg = json.load(f)
        return str(cfg["robot"]), int(cfg["idle"])
    except (OSError, ValueError, KeyError, TypeError):
        return None, 0


def openvpn_view(robot, status_path, now_wall, since_wall=0.0):
    """(serving, robot connected) from OpenVPN's status file, if written since `since_wall` (this
    agent's start: a file the previous boot's OpenVPN wrote on its way down is not this boot's)."""
    try:
        mtime = os.stat(status_path).st_mtime
        if now_wall - mtime > STATUS_FRESH or mtime < since_wall:
            return False, False
        with open(status_path) as f:
            return True, any(line.split(",")[:2] == ["CLIENT_LIST", robot] for line in f)
    except OSError:
        return False, False


class Idle:
    """The idle clock (monotonic seconds: a wall-clock jump must not stop a clone)."""

    def __init__(self, now):
        self.boot, self.since, self.setting = now, None, None

    def check(self, now, robot, idle, serving, robot_connected):
        """Seconds the robot has been away when that reached `idle`, else None."""
        if (robot, idle) != self.setting:
            self.setting = (robot, idle)
            if self.since is not None:
                self.since = now
        if (serving and self.since is None) or robot_connected:
            self.since = now
        if not idle:
            return None
        if self.since is None:
            away = now - self.boot
            return away if away >= max(idle, UNCONFIGURED) else None
        away = now - self.since
        return away if away >= idle else None


BOOT_LINE = "watching this boot"


def stop(robot, idle, away, note_path):
    line = (f"ccrp-autostop: {datetime.now(timezone.utc).isoformat(timespec='seconds')} robot {robot} not "
            f"connected for {away:.0f} s (idle {idle} s): stopping this clone")
    os.makedirs(os.path.dirname(note_path), exist_ok=True)
    tmp = note_path + ".tmp"
    with open(tmp, "w") as f:
        f.write(line + "\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, note_path)
    print(line, flush=True)  # the unit sends it to the journal and the console
    subprocess.run(["systemctl", "poweroff"], check=False)


def main(config=CONFIG, status=STATUS, note=NOTE, interval=5.0):
    # A note left by an earlier stop does not describe this boot's end.
    try:
        os.unlink(note)
    except FileNotFoundError:
        pass
    clock, started = Idle(time.monotonic()), time.time()
    # Marks this boot in the console, which on a cloud keeps the lines of every boot: a stop line
    # before this one is an earlier boot's, not why the clone stops next time (status reads it).
    print(f"ccrp-autostop: {BOOT_LINE}", flush=True)
    while True:
        robot, idle = read_config(config)
        serving, connected = openvpn_view(robot or "", status, time.time(), started)
        away = clock.check(time.monotonic(), robot, idle, serving, connected)
        if away is not None:
            stop(robot, idle, away, note)
            return 0
        time.sleep(interval)


if __name__ == "__main__":
    sys.exit(main())
