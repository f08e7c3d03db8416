"""The simulated robot's deadman (templates/edge/ccrp-demo-node and its ROS 2 twin): the node that
turns /cmd_vel into (stand-in) motor motion sets the motors to zero velocity when no command came
for 0.5 s while they move, so a key held on a page that lost its keyup, or a dashboard, clone or
link gone, does not keep the robot driving. A clock is injected: no test sleeps.

Each node is loaded as a module (ROS is imported in main() only); main() runs on stand-ins for
rospy and rclpy that hand back the subscription and the timer, to check the wiring too."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
import sys
import types

import pytest

from tests.conftest import ROOT

NODES = ["templates/edge/ccrp-demo-node", "templates/edge/ccrp-demo-node2"]


def load(path: str):
    name = "ccrp_demo_node_" + path.rsplit("-", 1)[-1]
    loader = importlib.machinery.SourceFileLoader(name, str(ROOT / path))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(name, loader))
    loader.exec_module(module)
    return module


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture(params=NODES)
def node(request, tmp_path, monkeypatch):
    module = load(request.param)
    monkeypatch.setattr(module, "CMD_LOG", str(tmp_path / "cmd_vel.log"))
    monkeypatch.setattr(module, "MOTORS", str(tmp_path / "motors"))
    module.log = lambda: [json.loads(line) for line in (tmp_path / "cmd_vel.log").read_text().splitlines()] \
        if (tmp_path / "cmd_vel.log").exists() else []
    return module


def test_the_motors_stop_when_no_command_came_for_half_a_second(node):
    clock = Clock()
    deadman = node.Deadman(clock=clock)
    assert node.DEADMAN_S == 0.5 and deadman.timeout == 0.5
    assert not deadman.expired()  # never commanded: nothing to stop
    deadman.command(0.2, 0.0)
    clock.t += 0.49
    assert not deadman.expired() and deadman.velocity == (0.2, 0.0)
    clock.t += 0.01
    assert deadman.expired() and deadman.velocity == (0.0, 0.0)
    clock.t += 10
    assert not deadman.expired()  # stopped once, not again and again


def test_each_command_renews_the_deadline_and_a_stop_needs_no_deadman(node):
    clock = Clock()
    deadman = node.Deadman(clock=clock)
    for _ in range(5):  # a held key, sent again every 0.2 s
        deadman.command(0.0, -0.5)
        clock.t += 0.2
        assert not deadman.expired()
    clock.t += 0.3
    assert deadman.expired()
    deadman.command(0.0, 0.0)  # the page's stop came first: nothing moves, nothing to stop
    clock.t += 5
    assert not deadman.expired()
    deadman.command(-0.1, 0.0)  # moving again after a deadman stop: stopped again
    clock.t += 0.5
    assert deadman.expired()


def test_the_check_drives_the_motors_to_zero_in_the_motion_log(node, tmp_path):
    clock = Clock()
    deadman = node.Deadman(clock=clock)
    deadman.command(0.2, 0.5)
    node.stop_if_silent(deadman)
    assert node.log() == []
    clock.t += 0.6
    node.stop_if_silent(deadman)
    node.stop_if_silent(deadman)
    (stop,) = node.log()
    assert (stop["linear"], stop["angular"], stop["deadman"], stop["motors"]) == (0.0, 0.0, True, "enabled")


class Msg(types.SimpleNamespace):
    pass


def twist(linear: float, angular: float) -> Msg:
    return Msg(linear=Msg(x=linear), angular=Msg(z=angular))


def fake_ros(monkeypatch) -> dict:
    """rospy, rclpy and the message modules, recording the cmd_vel callback and the timers."""
    seen: dict = {"timers": []}

    class Publisher:
        def __init__(self, *args, **kwargs) -> None:
            self.sent = []
            seen.setdefault("publishers", []).append((args, self))

        def publish(self, msg) -> None:
            self.sent.append(msg)

    def subscriber(topic, kind, callback, *args, **kwargs):
        seen[topic] = callback

    rospy = types.ModuleType("rospy")
    rospy.init_node = lambda *a, **k: None
    rospy.Publisher = Publisher
    rospy.Subscriber = subscriber
    rospy.Duration = lambda s: s
    rospy.Timer = lambda period, callback: seen["timers"].append((period, lambda: callback(None)))
    rospy.is_shutdown = lambda: True
    rospy.Rate = lambda hz: None

    class Node:
        def create_publisher(self, kind, topic, depth):
            return Publisher(topic)

        def create_subscription(self, kind, topic, callback, depth):
            seen[topic] = callback

        def create_timer(self, period, callback):
            seen["timers"].append((period, callback))

    rclpy = types.ModuleType("rclpy")
    rclpy.init = lambda: None
    rclpy.create_node = lambda name: Node()
    rclpy.spin = lambda node: None
    executors = types.ModuleType("rclpy.executors")
    executors.ExternalShutdownException = type("ExternalShutdownException", (Exception,), {})
    modules = {"rospy": rospy, "rclpy": rclpy, "rclpy.executors": executors}
    for name, attrs in (("geometry_msgs.msg", ["Twist"]), ("sensor_msgs.msg", ["Image"]), ("std_msgs.msg", ["String"])):
        module = types.ModuleType(name)
        for attr in attrs:
            setattr(module, attr, Msg)
        modules[name] = module
        modules[name.split(".")[0]] = types.ModuleType(name.split(".")[0])
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)
    return seen


def test_the_node_checks_its_deadman_well_within_the_timeout(node, monkeypatch):
    """main() on stand-ins: each /cmd_vel renews the deadline, a timer every DEADMAN_CHECK_S stops
    the motors once the commands stopped coming."""
    seen = fake_ros(monkeypatch)
    clock = Clock()
    real = node.Deadman
    monkeypatch.setattr(node, "Deadman", lambda: real(clock=clock))
    node.main()
    on_cmd = seen["cmd_vel"]
    checks = [cb for period, cb in seen["timers"] if period == node.DEADMAN_CHECK_S]
    assert len(checks) == 1 and node.DEADMAN_CHECK_S <= 0.1
    (check,) = checks
    on_cmd(twist(0.2, 0.0))
    clock.t += 0.3
    check()
    on_cmd(twist(0.2, 0.0))
    clock.t += 0.3
    check()
    assert [e.get("deadman", False) for e in node.log()] == [False, False]
    clock.t += 0.25
    check()
    check()
    log = node.log()
    assert [(e["linear"], e.get("deadman", False)) for e in log] == [(0.2, False), (0.2, False), (0.0, True)], log
