"""`ccrp robot teleop` and the dashboard's drive keys without a fleet running: what ccrp runs on
the clone (the agent pushed once, the operator unit started once for the dashboard and again when
it ended), what it reports, and refusals."""

from __future__ import annotations

import json

import pytest

from ccrp_cli.robot import evaluation
from ccrp_cli.errors import CcrpError, InputError


class Clone:
    def __init__(self, via="operator", reply=None):
        self.via, self.reply = via, reply
        self.pushed, self.ran = [], []

    def query(self):
        return {"nao1": object()}

    transport = property(lambda self: self)  # a fake clone is its own transport
    def push_files(self, robot, files, restart=()):
        self.pushed.append((robot, [f.dest for f in files]))

    def exec(self, robot, argv, timeout=60):
        self.ran.append(argv)
        if "teleop-send" in argv:
            i = argv.index("teleop-send")
            args = dict(zip(argv[i + 1::2], argv[i + 2::2]))
            out = self.reply or {"topic": "/" + args["--topic"], "linear": float(args["--linear"]),
                                 "angular": float(args["--angular"]), "acknowledged": True, "one_way_ms": 0.5,
                                 "round_trip_ms": 1.1, "via": self.via}
            return (3 if "error" in out else 0), "rospy noise\n" + json.dumps(out) + "\n"
        return 0, ""


@pytest.fixture(autouse=True)
def fresh():
    evaluation._pushed.clear()
    evaluation._operators.clear()


def units(clone):
    return [a for a in clone.ran if a[0] == "systemd-run"]


def test_one_command_from_the_cli(lab_up):
    fleet, _ = lab_up
    clone = Clone(via="one-shot")
    got = evaluation.send_command(fleet, clone, "nao1", 0.2, -0.5)
    assert got["robot"] == "nao1" and got["acknowledged"] and got["round_trip_ms"] == 1.1 and got["request_ms"] >= 0
    assert clone.pushed == [("nao1", [evaluation.AGENT])] and units(clone) == []  # no operator left behind
    send = clone.ran[-1]
    prefix = [*evaluation.AS_ROS, *evaluation.IN_ROS]
    assert send[:len(prefix)] == prefix  # argv, never a shell string with values in it
    assert send[len(prefix):] == ["teleop-send", "--topic", "cmd_vel", "--linear", "0.2", "--angular", "-0.5",
                                             "--timeout", "5"]


def test_the_dashboard_keeps_an_operator_and_starts_it_again_when_it_ended(lab_up):
    fleet, _ = lab_up
    clone = Clone(via="operator")
    for _ in range(3):
        evaluation.send_command(fleet, clone, "nao1", 0.2, 0, keep=True)
    assert len(units(clone)) == 1 and len(clone.pushed) == 1
    assert "teleop-operator" in units(clone)[0] and "ccrp-teleop" in units(clone)[0]
    clone.via = "one-shot"  # still starting (its socket not yet there): the command went alone
    evaluation.send_command(fleet, clone, "nao1", 0, 0, keep=True)
    assert len(units(clone)) == 1
    evaluation._operators[("lab", "nao1")] -= evaluation.TELEOP_START_S + 1  # ended (idle, the clone restarted)
    evaluation.send_command(fleet, clone, "nao1", 0, 0, keep=True)
    clone.via = "operator"
    evaluation.send_command(fleet, clone, "nao1", 0, 0, keep=True)
    assert len(units(clone)) == 2
    assert evaluation.stop_operators(fleet, clone) == ["nao1"]
    assert ["systemctl", "stop", "ccrp-teleop"] in clone.ran and not evaluation._operators


def test_refusals(lab_up):
    fleet, _ = lab_up
    with pytest.raises(CcrpError, match="nothing subscribes"):
        evaluation.send_command(fleet, Clone(reply={"error": "nothing subscribes to /cmd_vel on this master"}), "nao1", 0.1, 0)
    with pytest.raises(InputError, match="has no clone"):
        evaluation.send_command(fleet, Clone(), "nao2", 0.1, 0)
    with pytest.raises(InputError):
        evaluation.send_command(fleet, Clone(), "nobody", 0.1, 0)
    for linear, angular, topic in ((10.5, 0, "cmd_vel"), (float("inf"), 0, "cmd_vel"), (0, 0, "cmd vel"), (0, 0, "x;rm")):
        with pytest.raises(InputError):
            evaluation.check_command(linear, angular, topic)
    evaluation.check_command(-10, 10, "/mobile_base/cmd_vel")


def test_a_ros2_fleet_runs_the_same_agent_command(lab_up):
    """The agent picks rclpy itself where ros.env names no master (tests/e2e/test_jazzy_fleet.py)."""
    fleet, _ = lab_up
    fleet.inventory.ros.distro = "jazzy"
    clone = Clone()
    assert evaluation.send_command(fleet, clone, "nao1", 0.1, 0)["acknowledged"] is True
    prefix = [*evaluation.AS_ROS, *evaluation.IN_ROS]
    assert clone.ran[-1][:len(prefix)] == prefix and "teleop-send" in clone.ran[-1]


def test_the_operator_node_and_each_command_run_as_the_ros_user_not_root(lab_up):
    """The dashboard's operator node ran as root on the clone (a transient unit with no User=), its
    socket root's in /run. Now its unit runs as `ros`, as the camera agent's does, its socket in
    that user's 0700 runtime directory; a command without the operator runs its node through
    runuser as `ros`. Names and numbers are separate arguments after constants: no shell string is
    built from them."""
    import runpy

    from ccrp_cli.robot import camera
    from tests.conftest import ROOT

    fleet, _ = lab_up
    clone = Clone(via="operator")
    evaluation.send_command(fleet, clone, "nao1", 0.2, 0, keep=True)
    (unit,) = units(clone)
    props = [unit[i + 1] for i, a in enumerate(unit) if a == "--property"]
    assert "User=ros" in props and "RuntimeDirectory=ccrp-teleop" in props and "RuntimeDirectoryMode=0700" in props
    assert "NoNewPrivileges=yes" in props and not any(p.startswith("User=") and p != "User=ros" for p in props)
    assert [p for p in camera.UNIT_OPTIONS if p.startswith("User=")] == ["User=ros"]  # the camera agent's, alike
    command = unit[unit.index(evaluation.IN_ROS[0]):]
    assert command == [*evaluation.IN_ROS, "teleop-operator", "--topic", "cmd_vel", "--idle", "600"]
    # The agent's socket is in the unit's runtime directory, which systemd makes the `ros` user's.
    agent = runpy.run_path(str(ROOT / "templates/bench/ccrp-bench"), run_name="ccrp_bench")
    assert agent["TELEOP_SOCKET"].startswith("/run/ccrp-teleop/")
    send = clone.ran[-1]
    assert send[:4] == ["/usr/sbin/runuser", "-u", "ros", "--"] and "teleop-send" in send
    assert not any("nao1" in a for argv in clone.ran for a in argv)  # the shell text (ROS_PRELUDE) is a constant
