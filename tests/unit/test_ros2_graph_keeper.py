"""agent/ros2_graph.py's keeper (ccrp-graph.service) against a fake rclpy: it answers each question
on its socket with the graph, and starts a fresh participant when node names stay unknown (what a
long-lived Fast DDS participant showed after its robot's tunnel was down longer than the lease)."""

from __future__ import annotations

import importlib.util
import json
import socket
import sys
import threading
import time
import types
from pathlib import Path

import ccrp_cli.agent

PATH = Path(ccrp_cli.agent.__file__).parent / "ros2_graph.py"


class Info:
    def __init__(self, name: str, host: bytes) -> None:
        self.node_namespace, self.node_name = "/", name
        self.endpoint_gid = b"\x01\x0f" + host + b"\x00" * 20


class FakeNode:
    """A node in a graph where the robot's node is named, or unknown (a participant that lost it)."""

    def __init__(self, rclpy: FakeRclpy) -> None:
        self.rclpy, self.generation = rclpy, rclpy.inits

    def get_topic_names_and_types(self):
        return [("/chatter", ["std_msgs/msg/String"]), ("/rosout", ["rcl_interfaces/msg/Log"])]

    def get_publishers_info_by_topic(self, topic):
        robot = "_NODE_NAME_UNKNOWN_" if self.generation in self.rclpy.forgetful else "nao1_demo"
        if topic == "/rosout":  # the keeper itself, and a local node whose name never shows
            return [Info("ccrp_graph", b"\xaa\xaa"), Info("_NODE_NAME_UNKNOWN_", b"\xaa\xaa")]
        return [Info(robot, b"\xbb\xbb")]

    def get_subscriptions_info_by_topic(self, topic):
        return []

    def destroy_node(self):
        self.rclpy.destroyed += 1


class FakeRclpy(types.ModuleType):
    def __init__(self) -> None:
        super().__init__("rclpy")
        self.inits, self.destroyed, self.running = 1, 0, True
        self.forgetful = {1}  # participants that lost the robot's node names

    def ok(self):
        return self.running

    def try_shutdown(self):
        pass

    def init(self):
        self.inits += 1

    def create_node(self, name):
        return FakeNode(self)


def ask(path: Path) -> dict:
    with socket.socket(socket.AF_UNIX) as s:
        s.connect(str(path))
        return json.loads(s.recv(65536).decode())


def test_names_unknown_for_a_while_bring_a_fresh_participant(tmp_path, monkeypatch, capsys):
    fake = FakeRclpy()
    monkeypatch.setitem(sys.modules, "rclpy", fake)
    spec = importlib.util.spec_from_file_location("ccrp_graph_keeper", PATH)
    keeper = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(keeper)
    monkeypatch.setattr(keeper, "RENEW_AFTER", 0.3)
    monkeypatch.setattr(keeper, "RENEW_EVERY", 1.0)
    sock = tmp_path / "graph.sock"
    ended = []
    thread = threading.Thread(target=lambda: ended.append(keeper.serve(FakeNode(fake), str(sock))), daemon=True)
    thread.start()
    for _ in range(100):
        if sock.exists():
            break
        time.sleep(0.02)
    first = ask(sock)
    # Names the graph does not know are left out (the local one stays so: no renewal for it).
    assert first["nodes"] == {} and "/chatter" in first["published_topics"] and fake.inits == 1
    ask(sock)  # still unknown, not for long enough: the same participant
    assert fake.inits == 1
    time.sleep(0.4)
    ask(sock)  # unknown for longer than RENEW_AFTER: this answer as it was, then a fresh participant
    assert fake.inits == 2 and fake.destroyed == 1
    assert ask(sock)["nodes"] == {"/nao1_demo": "remote"}  # the fresh one names the robot's node
    assert "a fresh participant" in capsys.readouterr().err
    # A fresh one that does not help either: not renewed again before RENEW_EVERY.
    fake.forgetful = {2, 3}
    ask(sock)
    time.sleep(0.4)
    ask(sock)
    assert fake.inits == 2
    time.sleep(0.7)
    ask(sock)
    assert fake.inits == 3
    # A local node's unknown name alone (seen on Docker clones for as long as it ran) renews nothing.
    fake.forgetful = set()
    time.sleep(1.1)
    ask(sock)
    time.sleep(0.4)
    assert ask(sock)["nodes"] == {"/nao1_demo": "remote"} and fake.inits == 3
    fake.running = False
    thread.join(timeout=5)
    assert ended and ended[0].generation == 3  # serve hands back the node it ended with, for main to destroy
