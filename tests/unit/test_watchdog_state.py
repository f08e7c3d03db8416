"""The robot's watchdog in `ccrp status` and on the dashboard: its state read from a simulated
robot (or inferred from the clone for a real one), the brainless alert, and the fleet's alerts
(status rows + PKI) that `ccrp status` lists under its table."""

from __future__ import annotations

import datetime as dt
import json

from ccrp_cli.robot import watchdog
from ccrp_cli.alerts import fleet_alerts, row_alerts
from ccrp_cli.models.status import Power, StatusRow

T = 1795000000.25
SINCE = dt.datetime.fromtimestamp(T, dt.timezone.utc).isoformat(timespec="seconds")


def out(state: str | None, motors: str | None) -> str:
    return f"{watchdog.STATE_FILE} {state or ''}\n{watchdog.MOTORS_FILE} {motors or ''}\n"


def test_the_state_files_of_a_simulated_robot():
    assert watchdog.parse(out(f"ok {T}", None)).model_dump() == {
        "state": "connected", "since": SINCE, "source": "simulated robot", "motors": "enabled"}
    got = watchdog.parse(out(f"lost {T}", f"stopped {T}"))
    assert got.state == "brainless" and got.since == SINCE and got.motors == "stopped"
    assert watchdog.parse(out(None, None)).state == "starting"  # before the watchdog's first check
    assert watchdog.parse(out("garbage", None)).state == "starting"
    assert watchdog.parse(out(f"ok {T}", None)).since.endswith("+00:00")
    assert watchdog.parse(out("lost notatime", None)).model_dump() == {
        "state": "brainless", "since": None, "source": "simulated robot", "motors": "enabled"}


def test_a_real_robot_is_seen_from_its_clone():
    assert watchdog.inferred(base_row()).state == "connected"
    assert watchdog.inferred(base_row(vpn_connected=False)).state == "unknown"
    assert watchdog.inferred(base_row(master_reachable=False)).state == "unknown"
    assert watchdog.cell(watchdog.inferred(base_row())) == "connected (seen from clone)"
    assert watchdog.cell(watchdog.inferred(base_row(vpn_connected=False))) == "-"
    assert watchdog.cell(watchdog.parse(out(f"lost {T}", f"stopped {T}"))) == f"brainless since {SINCE[11:19]} (motors stopped)"


def base_row(**changes) -> StatusRow:
    row = {"robot": "nao1", "clone": "cri-nao1", "status": "running", "state": "running", "phase": "ready",
           "common_ip": "10.90.0.10", "vpn_subnet": "10.80.1.0/24", "ros_distro": "noetic", "vpn_connected": True,
           "secrets": True, "master_reachable": True, "relay_running": True,
           "watchdog": watchdog.parse(out(f"ok {T}", None))}
    return StatusRow(**(row | changes))


def test_a_brainless_robot_is_an_alert_also_when_its_clone_is_down():
    lost = watchdog.parse(out(f"lost {T}", f"stopped {T}"))
    assert [a["kind"] for a in row_alerts(base_row())] == []
    alerts = row_alerts(base_row(status="exited", state="stopped", vpn_connected=False, watchdog=lost))
    assert [a["kind"] for a in alerts] == ["clone-down", "robot-brainless"]
    assert alerts[1]["level"] == "error" and alerts[1]["robot"] == "nao1"
    assert alerts[1]["text"] == (f"nao1 is brainless since {SINCE[11:19]} UTC: its watchdog lost the clone and ran "
                                 "its fallback (motors stopped)")
    assert [a["kind"] for a in row_alerts(base_row(watchdog=watchdog.inferred(base_row(vpn_connected=False))))] == []


class Host:
    """This host's simulated robots as Sims sees them (providers.robot_host): nao1's brainless,
    turtlebot1's removed between the listing and the read."""

    def __init__(self):
        self.listed: list[bool] = []
        self.ran: list = []

    def names(self, running=False):
        self.listed.append(running)
        return ["nao1", "turtlebot1"]

    def exec(self, robot, argv, timeout=60, role="robot-sim"):
        self.ran.append((robot, argv, role))
        if robot == "turtlebot1":
            from ccrp_cli.errors import CcrpError

            raise CcrpError("container gone")
        return 0, out(f"lost {T}", f"stopped {T}")


def test_simulated_robots_are_read_in_their_containers(lab_up, monkeypatch):
    from ccrp_cli import providers
    from ccrp_cli.errors import CcrpError

    fleet, _ = lab_up
    host = Host()
    monkeypatch.setattr(providers, "robot_host", lambda name: host if name == fleet.name else None)
    got = watchdog.simulated(fleet, object())
    assert {r: w.model_dump() for r, w in got.items()} == {
        "nao1": {"state": "brainless", "since": SINCE, "source": "simulated robot", "motors": "stopped"}}
    assert host.listed == [True]  # the running ones
    assert all(role == "robot-sim" and argv == watchdog.READ for _, argv, role in host.ran)

    def no_engine(name):
        raise CcrpError("cannot reach the Docker engine")

    monkeypatch.setattr(providers, "robot_host", no_engine)
    assert watchdog.simulated(fleet, object()) == {}  # no Docker to ask: no simulated robots


def test_fleet_alerts_join_rows_and_pki_most_serious_first(lab_up):
    fleet, _ = lab_up
    lost = watchdog.parse(out(f"lost {T}", f"stopped {T}"))
    rows = [base_row(), base_row(robot="nao2", vpn_connected=False), base_row(robot="turtlebot1", status="exited", state="stopped",
                                                                              vpn_connected=False, watchdog=lost)]
    alerts = fleet_alerts(fleet, rows)
    got = [(a["level"], a["kind"], a["robot"]) for a in alerts]
    assert got[:3] == [("error", "clone-down", "turtlebot1"), ("error", "robot-brainless", "turtlebot1"),
                       ("warning", "robot-disconnected", "nao2")]
    # lab_up issued the relay certificates for 30 days (as a test): near expiry, after the row alerts
    assert {k for _, k, _ in got[3:]} == {"cert-expiry"} and {lvl for lvl, _, _ in got[3:]} == {"warning"}
    json.dumps(alerts)  # what --json prints


def test_the_power_device_report_and_what_it_changes(lab_up):
    import time

    from ccrp_cli.robot import power

    now = time.time()
    report = lambda relay, robot, t: json.dumps({"relay": relay, "robot": robot, "t": t, "device_t": t})  # noqa: E731
    p = power.parse_report(report("off", "off", now - 1))
    assert p["relay"] == "off" and p["robot"] == "off" and not p["silent"] and p["age_s"] < 3
    assert watchdog.power_cell(Power(**p)) == "off"
    silent = power.parse_report(report("on", "running", now - 30))
    assert silent["silent"] and watchdog.power_cell(Power(**silent)).startswith("on (device silent for")
    assert watchdog.power_cell(Power(**power.parse_report(report("on", "starting", now)))) == "on (robot starting)"
    assert watchdog.power_cell(watchdog.NO_DEVICE_YET) == "on (device not started)"
    assert watchdog.power_cell(None) == "-"
    for bad in ("", "{", '{"relay": "maybe", "robot": "off", "t": 1}', '{"relay": "on", "robot": "off"}'):
        assert power.parse_report(bad) is None, bad
    # Powered off on purpose: an info alert instead of the disconnection warning; a silent device warns.
    off = base_row(vpn_connected=False, power=p, watchdog={"state": "off", "since": p["reported_at"],
                                                           "source": "power device", "motors": None})
    assert off.power.relay == "off" and off.watchdog.state == "off"
    assert [(a["level"], a["kind"]) for a in row_alerts(off)] == [("info", "robot-powered-off")]
    assert [a["kind"] for a in row_alerts(base_row(power=silent))] == ["power-device-silent"]
    assert watchdog.cell(off.watchdog) == "off (robot powered off)"
    # Joined into a status row: a robot its device reports off runs no watchdog, whatever its
    # simulated robot's state file says; a simulated robot without a device yet has power on.
    lost = watchdog.parse(out(f"lost {T}", f"stopped {T}"))
    row = base_row(vpn_connected=False, power=p)
    watchdog.join(row, lost)
    assert row.watchdog.state == "off" and row.watchdog.source == "power device"
    row = base_row(watchdog=None)
    watchdog.join(row, lost)
    assert row.watchdog == lost and row.power == watchdog.NO_DEVICE_YET
    real = base_row(vpn_connected=False, watchdog=None)
    watchdog.join(real, None)  # a real robot without a device: no power column
    assert real.power is None and real.watchdog.state == "unknown"


def test_robot_power_refuses_bad_input(ccrp, tmp_path, lab_up):
    r = ccrp("robot", "power", "reboot", "-i", str(tmp_path / "none.yaml"), "--robot", "nao1")
    assert r.returncode == 2 and r.stderr.startswith("ccrp: error: robot power 'reboot'") and "Traceback" not in r.stderr
    r = ccrp("robot", "power", "off", "-i", str(tmp_path / "none.yaml"), "--robot", "nao1", "--out", str(tmp_path / "x"))
    assert r.returncode == 2 and "--out and --remote go with `robot power bundle`" in r.stderr and not (tmp_path / "x").exists()
    from ccrp_cli.robot import power
    from ccrp_cli.errors import InputError

    fleet, _ = lab_up
    import pytest

    with pytest.raises(InputError, match="unknown robot|not in|nobody"):
        power.power(fleet, "nobody", "off")
