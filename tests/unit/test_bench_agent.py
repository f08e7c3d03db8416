"""The bench agent (templates/bench/ccrp-bench) on its own, with stand-ins for rospy and rclpy
that record what the agent asks of them: the side it takes, each stream's QoS on ROS 1 and its
mapping on ROS 2 (docs/evaluation.md), and a ROS 2 role stopped by SIGTERM (`systemctl stop`)
ending its node before the interpreter exits (rclpy aborts the process otherwise)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from tests.conftest import ROOT

AGENT = ROOT / "templates" / "bench" / "ccrp-bench"

# Each module records its calls as JSON lines in $FAKE_ROS_LOG.
FAKES = {
    "_fakelog.py": """
        import json, os
        def log(*event):
            with open(os.environ["FAKE_ROS_LOG"], "a") as fh:
                fh.write(json.dumps(event) + "\\n")
    """,
    "std_msgs/__init__.py": "",
    "std_msgs/msg.py": """
        class String:
            def __init__(self, data=""):
                self.data = data
    """,
    "rclpy/__init__.py": """
        import time
        from _fakelog import log
        class _Node:
            def create_publisher(self, cls, topic, qos):
                log("publisher", topic, qos.kw)
                return type("P", (), {"publish": lambda s, m: None, "get_subscription_count": lambda s: 0})()
            def create_subscription(self, cls, topic, cb, qos):
                log("subscription", topic, qos.kw)
            def count_publishers(self, topic):
                return 0
            def destroy_node(self):
                log("destroy_node")
        def init(signal_handler_options=None):
            log("init", signal_handler_options)
        def create_node(name):
            log("create_node", name)
            return _Node()
        def spin_once(node, timeout_sec=None):
            time.sleep(timeout_sec)
        def shutdown():
            log("shutdown")
    """,
    "rclpy/signals.py": """
        class SignalHandlerOptions:
            NO = "NO"
    """,
    "rclpy/qos.py": """
        import enum
        class QoSProfile:
            def __init__(self, **kw):
                self.kw = {k: getattr(v, "name", v) for k, v in kw.items()}
        DurabilityPolicy = enum.Enum("DurabilityPolicy", "VOLATILE TRANSIENT_LOCAL")
        HistoryPolicy = enum.Enum("HistoryPolicy", "KEEP_LAST KEEP_ALL")
        ReliabilityPolicy = enum.Enum("ReliabilityPolicy", "RELIABLE BEST_EFFORT")
    """,
    "geometry_msgs/__init__.py": "",
    "geometry_msgs/msg.py": """
        class _Any:
            def __init__(self, **kw):
                self.__dict__.update(kw)
            def __getattr__(self, name):
                value = _Any()
                setattr(self, name, value)
                return value
        TwistStamped = _Any
    """,
    "sensor_msgs/__init__.py": "",
    "sensor_msgs/msg.py": "from geometry_msgs.msg import _Any as Image\n",
    "rospy/__init__.py": """
        from _fakelog import log
        def init_node(name, anonymous=False, disable_signals=False):
            log("init_node", name)
        import os, time
        _start = time.time()
        class Publisher:
            def __init__(self, topic, cls, queue_size=None, tcp_nodelay=False):
                log("publisher", topic, {"queue_size": queue_size, "tcp_nodelay": tcp_nodelay})
                self.topic = topic
            def publish(self, msg):
                log("publish", self.topic, time.time() - _start)
            def get_num_connections(self):
                # A subscriber connects FAKE_CONNECT_AFTER s after the process started (never: unset).
                after = os.environ.get("FAKE_CONNECT_AFTER")
                return int(after is not None and time.time() - _start >= float(after))
        class Subscriber:
            def __init__(self, topic, cls, cb, queue_size=None, tcp_nodelay=False):
                log("subscription", topic, {"queue_size": queue_size, "tcp_nodelay": tcp_nodelay})
            def get_num_connections(self):
                return 0
        def spin():
            while True:
                time.sleep(1)
        class Time:
            @staticmethod
            def from_sec(t):
                return t
    """,
}


@pytest.fixture
def fakes(tmp_path):
    for name, text in FAKES.items():
        path = tmp_path / "fakes" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return tmp_path


def serve(fakes, env: dict) -> list:
    """The clone's `serve` role until it says it serves, then SIGTERM: its exit code and calls."""
    log = fakes / "calls.jsonl"
    env = {"PATH": os.environ["PATH"], "PYTHONPATH": str(fakes / "fakes"), "FAKE_ROS_LOG": str(log), **env}
    proc = subprocess.Popen([sys.executable, str(AGENT), "serve"], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline() == "serving\n", proc.stderr.read()
        time.sleep(0.3)  # in its spin
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=10)
    finally:
        proc.kill()
        proc.wait()
    return rc, [json.loads(line) for line in log.read_text().splitlines()]


def test_on_ros2_the_agent_takes_rclpy_with_tcpros_semantics_and_ends_its_node_on_sigterm(fakes):
    rc, calls = serve(fakes, {})  # no ROS_MASTER_URI: ROS 2
    assert rc == 0, calls
    bulk = {"depth": 100, "history": "KEEP_LAST", "reliability": "RELIABLE", "durability": "VOLATILE"}
    assert ["publisher", "/ccrp_bench/reply", bulk] in calls and ["subscription", "/ccrp_bench/request", bulk] in calls
    assert calls[0] == ["init", "NO"]  # rclpy's own signal handlers off: the agent's end the node
    assert [c[0] for c in calls[-2:]] == ["destroy_node", "shutdown"], calls


def test_on_ros1_the_agent_takes_rospy_with_the_same_streams(fakes):
    rc, calls = serve(fakes, {"ROS_MASTER_URI": "http://cri-nao1:11311"})
    assert rc == -signal.SIGTERM, calls  # rospy's process ends by the signal, as before
    bulk = {"queue_size": 100, "tcp_nodelay": False}
    assert calls == [["init_node", "ccrp_bench_serve"], ["publisher", "/ccrp_bench/reply", bulk],
                     ["subscription", "/ccrp_bench/request", bulk]]


def test_a_teleop_role_starts_its_clock_once_the_other_end_has_connected(fakes):
    """Both ends start together and a node's connection takes seconds on a loaded host: the robot's
    camera waits for the operator's subscription before its `--duration` runs (a run whose
    connection took the whole duration measured nothing: 0 commands in a 3 s bench)."""
    log = fakes / "calls.jsonl"
    env = {"PATH": os.environ["PATH"], "PYTHONPATH": str(fakes / "fakes"), "FAKE_ROS_LOG": str(log),
           "ROS_MASTER_URI": "http://cri-nao1:11311", "FAKE_CONNECT_AFTER": "1.0"}
    proc = subprocess.run([sys.executable, str(AGENT), "teleop-robot", "--duration", "0.6"], env=env,
                          capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr
    sent = [c[2] for c in map(json.loads, log.read_text().splitlines()) if c[0] == "publish"]
    assert sent and min(sent) >= 1.0 and json.loads(proc.stdout.splitlines()[-1])["frames_sent"] == len(sent)

