"""Autostop (issue 16): the inventory's setting, and the clone-side agent's idle clock."""

from __future__ import annotations

import json
import os
import time

import pytest

from ccrp_cli.agent import autostop
from ccrp_cli.errors import CcrpError
from ccrp_cli.loader import parse_inventory
from ccrp_cli.models.inventory import Robot
from ccrp_cli.providers.base import autostop_note

BASE = {"fleet": "f", "provider": {"kind": "docker"}, "robots": [{"name": "nao1"}, {"name": "nao2"}]}


def inv(**extra):
    return parse_inventory({**BASE, **extra}, "ccrp.yaml")


def test_idle_is_a_duration_with_a_unit_and_a_robot_replaces_the_fleets():
    fleet = inv(autostop={"idle": "30m"}, robots=[{"name": "nao1"}, {"name": "nao2", "autostop": {"idle": "never"}},
                                                  {"name": "nao3", "autostop": {"idle": "90s"}}],
                template={"prefix": "bot", "autostop": {"idle": "2h"}})
    assert [fleet.idle_of(r) for r in fleet.robots] == [1800, 0, 90]
    assert fleet.idle_of(Robot(name="bot1", autostop=fleet.template.autostop)) == 7200
    assert inv().idle_of(Robot(name="nao1")) == 0  # off unless asked for


@pytest.mark.parametrize("idle, why", [
    (30, "30 has no unit: write it as 30s or 30m"),
    ("10s", "idle must be between 30s and 30d, or never"),
    ("31d", "idle must be between 30s and 30d, or never"),
    ("30 min", "is not a duration"),
    (True, "valid integer"),
])
def test_a_bad_idle_is_one_line_naming_the_key(idle, why):
    with pytest.raises(CcrpError) as err:
        inv(autostop={"idle": idle})
    assert "autostop.idle" in err.value.one_line() and why in err.value.one_line()
    assert "\n" not in err.value.one_line()


def test_the_clock_runs_from_openvpn_serving_the_robots_last_session_or_the_settings_change():
    clock = autostop.Idle(now=0)
    assert clock.check(20, "nao1", 60, False, False) is None  # booted, keys not pushed yet: not idle
    assert clock.check(40, "nao1", 60, True, False) is None  # configured: the robot has 60 s from now
    assert clock.check(99, "nao1", 60, True, False) is None
    assert clock.check(100, "nao1", 60, True, False) == 60
    assert clock.check(110, "nao1", 60, True, True) is None  # the robot came
    assert clock.check(169, "nao1", 60, True, False) is None
    assert clock.check(170, "nao1", 60, True, False) == 60
    assert clock.check(175, "nao1", 90, True, False) is None  # a new setting: a full 90 s from now
    assert clock.check(265, "nao1", 90, True, False) == 90
    assert clock.check(266, "nao1", 0, True, False) is None  # never
    assert clock.check(10_000, "nao1", 0, True, False) is None


def test_a_clone_nobody_configures_stops_after_the_longer_of_idle_and_ten_minutes():
    clock = autostop.Idle(now=0)  # a cloud clone started from the console: its keys never come
    assert clock.check(599, "nao1", 60, False, False) is None
    assert clock.check(600, "nao1", 60, False, False) == 600
    clock = autostop.Idle(now=0)
    assert clock.check(1799, "nao1", 1800, False, False) is None
    assert clock.check(1800, "nao1", 1800, False, False) == 1800


def test_openvpn_view_reads_the_status_file_and_distrusts_an_old_one(tmp_path):
    status = tmp_path / "status.log"
    assert autostop.openvpn_view("nao1", str(status), time.time()) == (False, False)  # OpenVPN never wrote it
    status.write_text("TITLE,OpenVPN 2.6\nHEADER,CLIENT_LIST,Common Name\n"
                      "CLIENT_LIST,nao1,198.51.100.7:40000,10.80.0.2\nCLIENT_LIST,nao10,x\nEND\n")
    assert autostop.openvpn_view("nao1", str(status), time.time()) == (True, True)
    assert autostop.openvpn_view("nao2", str(status), time.time()) == (True, False)
    assert autostop.openvpn_view("nao", str(status), time.time()) == (True, False)  # whole names only
    # Written 10 s ago, by the OpenVPN of the boot before (a clone started again within seconds):
    # not this boot's server.
    recent = time.time() - 10
    os.utime(status, (recent, recent))
    assert autostop.openvpn_view("nao1", str(status), time.time(), since_wall=time.time() - 5) == (False, False)
    assert autostop.openvpn_view("nao1", str(status), time.time(), since_wall=time.time() - 60) == (True, True)
    old = time.time() - autostop.STATUS_FRESH - 5
    os.utime(status, (old, old))  # OpenVPN stopped rewriting it: it is not serving anyone
    assert autostop.openvpn_view("nao1", str(status), time.time()) == (False, False)


def test_the_agent_notes_why_and_powers_off_once_the_robot_stayed_away(tmp_path, monkeypatch):
    config, note = tmp_path / "autostop.json", tmp_path / "lib" / "autostop.note"
    config.write_text(json.dumps({"robot": "nao1", "idle": 30}))
    note.parent.mkdir()
    note.write_text("ccrp-autostop: from the boot before\n")
    ran, now = [], [1000.0]
    monkeypatch.setattr(autostop.subprocess, "run", lambda argv, check: ran.append(argv))
    monkeypatch.setattr(autostop.time, "monotonic", lambda: now[0])

    def sleep(seconds):
        assert not note.exists()  # the old note went at start
        status.write_text("TITLE,OpenVPN 2.6\nEND\n")  # this boot's OpenVPN: serving, nobody connected
        now[0] += seconds

    monkeypatch.setattr(autostop.time, "sleep", sleep)
    status = tmp_path / "status.log"
    status.write_text("TITLE,OpenVPN 2.6\nCLIENT_LIST,nao1,x\nEND\n")  # the boot before's: not counted
    assert autostop.main(str(config), str(status), str(note), interval=5) == 0
    assert ran == [["systemctl", "poweroff"]] and now[0] == 1035  # serving from the first rewrite, at 1005
    line = note.read_text()
    assert "robot nao1 not connected for 30 s (idle 30 s)" in line
    assert autostop_note(f"boot noise\n{line}more noise\n").endswith("stopping this clone")


def test_a_cloud_console_of_several_boots_names_only_this_boots_stop(capsys, tmp_path, monkeypatch):
    """A cloud's console keeps every boot: an autostop line of an earlier boot must not make a
    clone the operator stopped later (`clone stop`) read as `stopped (idle)`."""
    config = tmp_path / "autostop.json"
    config.write_text(json.dumps({"robot": "nao1", "idle": 0}))  # never: the agent only watches
    monkeypatch.setattr(autostop.time, "sleep", lambda s: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.raises(KeyboardInterrupt):
        autostop.main(str(config), str(tmp_path / "status"), str(tmp_path / "note"))
    boot = capsys.readouterr().out  # what the agent puts on the console as it starts
    stop = "ccrp-autostop: 2026-11-23T08:35:44+00:00 robot nao1 not connected for 30 s (idle 30 s): stopping this clone\n"
    assert autostop_note(boot + "noise\n" + stop).endswith("stopping this clone")  # stopped idle
    assert autostop_note(boot + stop + "reboot noise\n" + boot) is None  # started again, then stopped by hand
    assert autostop_note(boot + stop + boot + stop).endswith("stopping this clone")


def test_a_missing_or_garbled_config_means_never(tmp_path):
    assert autostop.read_config(str(tmp_path / "none.json")) == (None, 0)
    (tmp_path / "bad.json").write_text("{")
    assert autostop.read_config(str(tmp_path / "bad.json")) == (None, 0)
    clock = autostop.Idle(now=0)
    assert clock.check(10**6, None, 0, False, False) is None


class Clones:
    """A provider: nao1 stopped by its autostop agent, nao2 running but not answering (shutting
    down), turtlebot1 running and healthy."""

    max_parallel = 3

    def query(self):
        from ccrp_cli.providers.base import CloneRecord, CloneState

        states = {"nao1": (CloneState.STOPPED, "SHUTOFF"), "nao2": (CloneState.RUNNING, "ACTIVE"),
                  "turtlebot1": (CloneState.RUNNING, "ACTIVE")}
        return {r: CloneRecord(robot=r, provider_id=r, state=s, status=word) for r, (s, word) in states.items()}

    def stop_note(self, robot):
        return "2026-11-23T05:00:00+00:00 robot nao1 not connected for 31 s (idle 30 s): stopping this clone" \
            if robot == "nao1" else None

    transport = property(lambda self: self)  # a fake clone is its own transport

    def timeout_scale(self, robot):
        return 1

    def exec(self, robot, argv, timeout=60):
        if robot == "nao2":
            raise CcrpError("SSH to ccrp@192.0.2.5 failed: Unable to connect to port 22")
        return 0, json.dumps({"vpn": {"up": True, "clients": []}, "master": {"reachable": True, "nodes": {}}})


def test_status_shows_a_clone_stopped_idle_and_one_that_does_not_answer(lab_up):
    from ccrp_cli.ops.status import fleet_status

    fleet, _ = lab_up
    rows = {r.robot: r for r in fleet_status(fleet, Clones())}
    assert rows["nao1"].status == "stopped (idle)" and "not connected for 31 s" in rows["nao1"].stopped_idle
    assert rows["nao2"].status == "ACTIVE (unreachable)" and "port 22" in rows["nao2"].unreachable
    assert rows["turtlebot1"].master_reachable is True and rows["turtlebot1"].unreachable is None


class Garbled(Clones):
    """nao2 answers with a health report that is not one (a node without a name, a power device
    word ccrp does not know): what a tampered agent's status file on the clone could give."""

    def exec(self, robot, argv, timeout=60):
        if robot == "nao2":
            return 0, json.dumps({"vpn": {"up": True, "clients": []}, "master": {"reachable": True, "nodes": {}},
                                  "nodes": [{"state": "active"}]})
        return super().exec(robot, argv, timeout)


def test_a_malformed_health_report_marks_its_row_not_the_whole_status(lab_up):
    from ccrp_cli.ops.status import fleet_status

    fleet, _ = lab_up
    rows = {r.robot: r for r in fleet_status(fleet, Garbled())}
    assert rows["nao2"].status == "ACTIVE (unreachable)"
    assert rows["nao2"].unreachable == "its health report is malformed (ValidationError)" and rows["nao2"].nodes is None
    assert rows["turtlebot1"].master_reachable is True and rows["turtlebot1"].unreachable is None
