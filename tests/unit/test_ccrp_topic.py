"""`ccrp-topic pub` (templates/image/ccrp-topic) behaves as the distro's own tool: `ros2 topic pub`
(1 Hz until stopped; --once, --times N, --rate HZ) on ROS 2, `rostopic pub` (once, latched, until
stopped; -1, -r HZ) on ROS 1, and the -n COUNT -r HZ of scripts written before keeps its meaning."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import subprocess
import sys

import pytest

from tests.conftest import ROOT

TOOL = ROOT / "templates" / "image" / "ccrp-topic"


@pytest.fixture(scope="module")
def tool():
    loader = importlib.machinery.SourceFileLoader("ccrp_topic_tool", str(TOOL))
    spec = importlib.util.spec_from_loader("ccrp_topic_tool", loader)
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def plan(tool, *flags: str, ros2: bool):
    cmd, pos, opts = tool.parse(["pub", "/chatter", "std_msgs/String", "hi", *flags])
    assert (cmd, pos) == ("pub", ["/chatter", "std_msgs/String", "hi"])
    return tool.pub_plan(opts, ros2)


@pytest.mark.parametrize("flags, ros2, expected", [
    # ROS 2, as `ros2 topic pub`: 1 Hz until stopped by default.
    ((), True, (None, 1.0, False)),
    (("--once",), True, (1, 1.0, False)),
    (("-1",), True, (1, 1.0, False)),
    (("--times", "3"), True, (3, 1.0, False)),
    (("-t", "3", "--rate", "5"), True, (3, 0.2, False)),
    (("-r", "4"), True, (None, 0.25, False)),
    # ROS 1, as `rostopic pub`: once, latched, until stopped; -1 exits; -r publishes until stopped.
    ((), False, (1, 1.0, True)),
    (("-1",), False, (1, 1.0, False)),
    (("-r", "10"), False, (None, 0.1, False)),
    # -n COUNT -r HZ of existing scripts: COUNT messages at HZ, then exit, on either.
    (("-n", "50", "-r", "5"), True, (50, 0.2, False)),
    (("-n", "50", "-r", "5"), False, (50, 0.2, False)),
])
def test_pub_follows_the_distros_own_tool(tool, flags, ros2, expected):
    assert plan(tool, *flags, ros2=ros2) == expected


def test_publish_sends_by_the_plan_and_runs_until_stopped_without_a_count(tool):
    sent, pauses = [], []
    assert tool.publish(lambda: sent.append(1), (3, 0.2, False), pauses.append) == 0
    assert len(sent) == 3 and pauses == [0.2, 0.2, 0.3]  # the last one gets 0.3 s to leave

    class Stopped(Exception):
        pass

    def pause(seconds):
        pauses.append(seconds)
        if len(pauses) == 5:
            raise Stopped  # stands for Ctrl-C / SIGTERM: nothing else ends it
    sent, pauses = [], []
    with pytest.raises(Stopped):
        tool.publish(lambda: sent.append(1), (None, 1.0, False), pause)
    assert len(sent) == 5 and pauses == [1.0] * 5
    sent, pauses = [], []
    with pytest.raises(Stopped):  # rostopic's latch mode: one message, then it stays
        tool.publish(lambda: sent.append(1), (1, 1.0, True), pause)
    assert len(sent) == 1 and pauses[0] == 0.3


def test_echo_keeps_its_count_and_timeout_and_data_may_start_with_a_dash(tool):
    assert tool.parse(["echo", "/a", "-n", "2", "-t", "5"]) == ("echo", ["/a"], {"n": 2, "t": 5.0})
    cmd, pos, opts = tool.parse(["pub", "/a", "std_msgs/String", "-x", "--once"])
    assert pos[2] == "-x" and opts["once"] is True
    assert tool.parse(["pub", "/a", "std_msgs/String", "--", "-1"])[1][2] == "-1"


@pytest.mark.parametrize("argv", [
    ["pub", "/a", "std_msgs/String", "x", "--once", "--times", "2"],
    ["pub", "/a", "std_msgs/String", "x", "--times", "0"],
    ["pub", "/a", "std_msgs/String", "x", "--rate", "0"],
    ["pub", "/a", "std_msgs/String", "x", "--rate", "fast"],
    ["pub", "--bogus", "/a", "std_msgs/String", "x"],
    ["echo", "/a", "--once"],
])
def test_bad_pub_and_echo_options_are_one_line(argv):
    proc = subprocess.run([sys.executable, str(TOOL), *argv], capture_output=True, text=True, timeout=30)
    assert proc.returncode == 2 and proc.stderr.startswith("ccrp-topic: error: ") and proc.stderr.count("\n") == 1, \
        (argv, proc.stderr)
