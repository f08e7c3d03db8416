"""The relay agent's ROS 2 side (ccrp_cli/agent/relay_ros2.py, docs/ros2.md): type names and QoS as
an exporting clone takes them from the graph and an importing clone publishes them again. rclpy
is not installed here: a small stand-in records what the agent asks of it (the real thing runs in
tests/e2e/test_jazzy_fleet.py)."""

from __future__ import annotations

import enum
import importlib.util
import json
import sys
import types
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.unit.helpers import load_agent

pytest.importorskip("zenoh")


class ReliabilityPolicy(enum.Enum):
    SYSTEM_DEFAULT, RELIABLE, BEST_EFFORT, UNKNOWN = range(4)


class DurabilityPolicy(enum.Enum):
    SYSTEM_DEFAULT, TRANSIENT_LOCAL, VOLATILE, UNKNOWN = range(4)


@dataclass
class QoSProfile:
    depth: int
    reliability: ReliabilityPolicy
    durability: DurabilityPolicy


@dataclass
class Info:
    """rclpy's TopicEndpointInfo, as far as the agent reads it."""
    topic_type: str
    reliability: str
    durability: str

    @property
    def qos_profile(self):
        return QoSProfile(10, ReliabilityPolicy[self.reliability], DurabilityPolicy[self.durability])


class String:
    pass


class Twist:
    pass


@dataclass
class Node:
    publishers: dict = field(default_factory=dict)
    subs: list = field(default_factory=list)
    pubs: list = field(default_factory=list)
    destroyed: list = field(default_factory=list)

    def get_publishers_info_by_topic(self, topic):
        return self.publishers.get(topic, [])

    def create_subscription(self, cls, topic, callback, qos, raw=False):
        self.subs.append((cls, topic, qos, raw))
        return ("sub", len(self.subs))

    def destroy_subscription(self, sub):
        self.destroyed.append(sub)

    def create_publisher(self, cls, topic, qos):
        pub = Pub(cls, topic, qos)
        self.pubs.append(pub)
        return pub

    def destroy_publisher(self, pub):
        self.destroyed.append(pub)

    def count_subscribers(self, topic):
        return 0


@dataclass
class Pub:
    cls: type
    topic: str
    qos: QoSProfile
    sent: list = field(default_factory=list)

    def publish(self, data):
        self.sent.append(data)

    def get_subscription_count(self):
        return 0


class Session:
    def __init__(self):
        self.puts, self.declared = [], []

    def declare_publisher(self, key, congestion_control):
        session = self
        self.declared.append((key, congestion_control))

        class P:
            def put(self, payload, attachment):
                session.puts.append((key, payload, json.loads(attachment)))

            def undeclare(self):
                pass
        return P()


@pytest.fixture
def agent(monkeypatch):
    """relay_ros2.py, importing relay.py as on a clone (both in one directory)."""
    monkeypatch.setitem(sys.modules, "relay", load_agent())
    # What message_class adds to the import system (WorkspaceInterfaces) goes with the test.
    monkeypatch.setattr(sys, "meta_path", list(sys.meta_path))
    monkeypatch.setattr(sys, "path_importer_cache", dict(sys.path_importer_cache))
    agents = Path(__file__).resolve().parents[2] / "ccrp_cli" / "agent"
    # Its loader of the workspace's message types, which fleet up pushes beside it.
    spec = importlib.util.spec_from_file_location("relay_interfaces", agents / "relay_interfaces.py")
    interfaces = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(interfaces)
    monkeypatch.setitem(sys.modules, "relay_interfaces", interfaces)
    spec = importlib.util.spec_from_file_location("relay_ros2", agents / "relay_ros2.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.interfaces = interfaces
    qos = types.ModuleType("rclpy.qos")
    qos.QoSProfile, qos.ReliabilityPolicy, qos.DurabilityPolicy = QoSProfile, ReliabilityPolicy, DurabilityPolicy
    msgs = {"std_msgs.msg": {"String": String}, "geometry_msgs.msg": {"Twist": Twist}}
    monkeypatch.setitem(sys.modules, "rclpy", types.ModuleType("rclpy"))
    monkeypatch.setitem(sys.modules, "rclpy.qos", qos)
    for name, classes in msgs.items():
        mod = types.ModuleType(name)
        for cls_name, cls in classes.items():
            setattr(mod, cls_name, cls)
        monkeypatch.setitem(sys.modules, name, mod)
    return module


def relay(agent, node):
    watched = []
    ros = types.SimpleNamespace(node=node, watched=watched, watch=watched.append, unwatch=watched.remove)
    r = types.SimpleNamespace(ros=ros, session=Session(), cfg={"robot": "nao1"})
    r.key = lambda source, topic: f"ccrp/lab/{source}/{topic.strip('/')}"
    return r


@pytest.mark.parametrize("name, parsed", [
    ("std_msgs/msg/String", ("std_msgs", "String")),
    ("sensor_msgs/Image", ("sensor_msgs", "Image")),
])
def test_message_type_names(agent, name, parsed):
    assert agent.message_type(name) == parsed


@pytest.mark.parametrize("name", ["std_msgs/srv/Empty", "os/msg/x;y", "../msg/String", "String", "a/msg/B/C", "",
                                  "std_msgs/msg/1String", "__import__('os')/msg/X"])
def test_a_type_name_that_is_not_a_message_is_refused(agent, name):
    # It comes from the graph or from a peer and is imported as a module: nothing else gets through.
    with pytest.raises(ValueError):
        agent.message_type(name)


def test_message_class_imports_the_generated_class(agent):
    assert agent.message_class("geometry_msgs/msg/Twist") is Twist


@pytest.mark.parametrize("offered, expected", [
    ([("reliable", "volatile")], ("reliable", "volatile")),
    ([("best_effort", "volatile")], ("best_effort", "volatile")),
    ([("reliable", "transient_local")], ("reliable", "transient_local")),
    # The weakest of several publishers: a reliable subscription would not match a best-effort
    # one, a transient-local one not a volatile one.
    ([("reliable", "transient_local"), ("best_effort", "transient_local")], ("best_effort", "transient_local")),
    ([("reliable", "transient_local"), ("reliable", "volatile")], ("reliable", "volatile")),
])
def test_the_qos_taken_is_the_weakest_offered(agent, offered, expected):
    assert agent.combined_qos(offered) == dict(zip(("reliability", "durability"), expected))


def test_qos_names_become_a_profile_and_unknown_ones_are_refused(agent):
    profile = agent.qos_profile({"reliability": "best_effort", "durability": "transient_local"})
    assert profile == QoSProfile(100, ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.TRANSIENT_LOCAL)
    for bad in ({"reliability": "system_default", "durability": "volatile"}, {"reliability": "reliable"}, {}):
        with pytest.raises(ValueError):
            agent.qos_profile(bad)


def test_an_export_subscribes_raw_once_published_with_the_publishers_type_and_qos(agent):
    node = Node()
    r = relay(agent, node)
    export = agent.Export2(r, "/chatter")
    assert node.subs == []  # nobody publishes it yet: nothing to subscribe to (no type)
    node.publishers["/chatter"] = [Info("std_msgs/msg/String", "BEST_EFFORT", "VOLATILE")]
    export.poll()
    export.poll()  # unchanged: subscribed once
    assert node.subs == [(String, "/chatter", QoSProfile(100, ReliabilityPolicy.BEST_EFFORT, DurabilityPolicy.VOLATILE), True)]
    assert r.ros.watched == [("sub", 1)]  # its samples are taken by the agent's spinner
    export.forward(b"\x00\x01\x00\x00hi")
    export.forward(b"\x00\x01\x00\x00ho")
    assert r.session.puts == [
        ("ccrp/lab/nao1/chatter", b"\x00\x01\x00\x00hi",
         {"t": "std_msgs/msg/String", "q": {"reliability": "best_effort", "durability": "volatile"}, "s": 1}),
        ("ccrp/lab/nao1/chatter", b"\x00\x01\x00\x00ho",
         {"t": "std_msgs/msg/String", "q": {"reliability": "best_effort", "durability": "volatile"}, "s": 2}),
    ]
    # Its publisher came back transient-local and reliable: subscribed again with that QoS.
    node.publishers["/chatter"] = [Info("std_msgs/msg/String", "RELIABLE", "TRANSIENT_LOCAL")]
    export.poll()
    assert node.destroyed == [("sub", 1)] and r.ros.watched == [("sub", 2)]
    assert node.subs[-1][2] == QoSProfile(100, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)


def test_a_reliable_topic_waits_for_room_towards_its_peers_and_a_best_effort_one_drops(agent):
    import zenoh

    node = Node(publishers={"/chatter": [Info("std_msgs/msg/String", "RELIABLE", "VOLATILE")]})
    r = relay(agent, node)
    export = agent.Export2(r, "/chatter")
    assert r.session.declared == [("ccrp/lab/nao1/chatter", zenoh.CongestionControl.BLOCK)]
    node.publishers["/chatter"] = [Info("std_msgs/msg/String", "RELIABLE", "TRANSIENT_LOCAL")]
    export.poll()  # the same reliability: the same Zenoh publisher
    assert len(r.session.declared) == 1
    node.publishers["/chatter"].append(Info("std_msgs/msg/String", "BEST_EFFORT", "VOLATILE"))
    export.poll()
    assert r.session.declared[-1] == ("ccrp/lab/nao1/chatter", zenoh.CongestionControl.DROP)
    # ROS 1 topics are TCP, reliable: the ROS 1 side always waits.
    assert agent.congestion(True) == zenoh.CongestionControl.BLOCK


def test_an_import_publishes_the_bytes_with_the_type_and_qos_that_came(agent):
    node = Node()
    imp = agent.Import2.__new__(agent.Import2)  # without its Zenoh subscriber and thread
    imp.relay, imp.local, imp.pub = relay(agent, node), "/nao1/chatter", None
    meta = {"t": "std_msgs/msg/String", "q": {"reliability": "reliable", "durability": "transient_local"}, "s": 1}
    imp._publish(meta, b"one")
    imp._publish(meta | {"s": 2}, b"two")
    assert len(node.pubs) == 1 and node.pubs[0].cls is String and node.pubs[0].topic == "/nao1/chatter"
    assert node.pubs[0].qos == QoSProfile(100, ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL)
    assert node.pubs[0].sent == [b"one", b"two"]  # as they came: no deserializing
    # The source's type changed: a publisher of the new type replaces the old one.
    imp._publish({"t": "geometry_msgs/msg/Twist", "q": {"reliability": "best_effort", "durability": "volatile"}, "s": 3},
                 b"three")
    assert node.destroyed == [node.pubs[0]] and node.pubs[1].cls is Twist and node.pubs[1].sent == [b"three"]
    with pytest.raises(ValueError):  # a peer's bad type name is refused before any import
        imp._publish({"t": "os/path/join", "q": meta["q"], "s": 4}, b"x")
    assert node.pubs[1].sent == [b"three"] and len(node.destroyed) == 1  # and the topic goes on


def test_a_type_this_clone_lacks_is_reported_once_and_not_subscribed(agent, capsys):
    node = Node(publishers={"/faces": [Info("face_msgs/msg/Face", "RELIABLE", "VOLATILE")]})
    export = agent.Export2(relay(agent, node), "/faces")
    export.poll()
    assert node.subs == [] and capsys.readouterr().err.count("cannot relay face_msgs/msg/Face") == 1
    node.publishers["/faces"] = [Info("std_msgs/msg/String", "RELIABLE", "VOLATILE")]
    export.poll()
    assert [s[0] for s in node.subs] == [String]


def test_the_agents_fastdds_profile_is_udp_unicast_to_this_host_and_the_robot(agent):
    """Shared memory fails between users (the agent runs as its own): its participant is UDP only,
    discovering as LOCALHOST + ROS_STATIC_PEERS do, with no multicast locator."""
    import xml.etree.ElementTree as ET

    text = agent.fastdds_profile("10.81.1.2; ;robot.example;10.81.1.2")
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    root = ET.fromstring(text)
    assert [t.text for t in root.findall(".//f:transport_descriptor/f:type", ns)] == ["UDPv4"]
    assert root.find(".//f:useBuiltinTransports", ns).text == "false"
    peers = [a.text for a in root.findall(".//f:initialPeersList//f:address", ns)]
    assert peers == ["127.0.0.1", "10.81.1.2"]  # a name is left out, a repeat once
    assert root.find(".//f:metatrafficMulticastLocatorList", ns) is None and "SHM" not in text
    # An image's datagrams all fit in its sockets (the kernel's default buffer dropped some).
    assert int(root.find(".//f:transport_descriptor/f:receiveBufferSize", ns).text) == 2 * 1024 * 1024
    # Its writers answer a subscriber's NACK of a lost fragment at once (the default waits 5 ms).
    writer = root.find("f:data_writer", ns)
    assert writer.get("is_default_profile") == "true"
    delay = writer.find("f:times/f:nackResponseDelay", ns)
    assert (delay.find("f:sec", ns).text, delay.find("f:nanosec", ns).text) == ("0", "0")


class Handle:
    """An rclpy entity's handle: held (a context manager) while waited on; destroyed, it refuses."""

    def __init__(self, owner, pointer):
        self.owner, self.pointer, self.held, self.destroyed = owner, pointer, 0, False

    def __enter__(self):
        if self.destroyed:
            raise InvalidHandle(self.pointer)
        self.held += 1
        return self

    def __exit__(self, *exc):
        self.held -= 1

    def take_message(self, msg_type, raw):
        assert raw and msg_type is String
        return (self.owner.queue.pop(0), "info") if self.owner.queue else None


class InvalidHandle(Exception):
    pass


class Sub:
    def __init__(self, pointer, callback, topic="/chatter"):
        self.handle, self.callback, self.topic_name = Handle(self, pointer), callback, topic
        self.msg_type, self.raw, self.queue = String, True, []


class Guard:
    def __init__(self):
        self.handle, self.triggered = Handle(self, "guard"), False

    def trigger(self):
        self.triggered = True


class Context:
    def __init__(self):
        self.handle, self.up = Handle(self, "context"), True

    def ok(self):
        return self.up


def spinner_world(agent, rounds):
    """A Spinner on stand-ins: each wait (the middleware) runs the next of `rounds`, which may
    queue samples or change the watched subscriptions; the context goes down after the last."""
    node = types.SimpleNamespace(context=Context(), guards=[])
    node.create_guard_condition = lambda cb: node.guards.append(Guard()) or node.guards[-1]
    waits = []

    class WaitSet:
        def __init__(self, subs, guards, *rest_and_context):
            assert guards == 1 and rest_and_context[:4] == (0, 0, 0, 0)
            self.subs, self.guards = [], []

        def clear_entities(self):
            self.subs, self.guards = [], []

        def add_subscription(self, handle):
            assert handle.held and not handle.destroyed  # held while waited on, as rclpy wants
            self.subs.append(handle)

        def add_guard_condition(self, handle):
            self.guards.append(handle)

        def wait(self, timeout):
            waits.append([h.pointer for h in self.subs])
            if not rounds:
                node.context.up = False
            else:
                rounds.pop(0)()

        def get_ready_entities(self, kind):
            if kind == "subscription":
                return [h.pointer for h in self.subs if h.owner.queue]
            guard = node.guards[0]
            ready, guard.triggered = guard.triggered, False
            return ["guard"] if ready else []

    spinner = agent.Spinner(node, types.SimpleNamespace(WaitSet=WaitSet), InvalidHandle)
    return spinner, waits


def test_the_spinner_takes_every_waiting_sample_and_follows_the_subscriptions(agent):
    got = []
    a = Sub("a", lambda data: got.append(("a", data)))
    b = Sub("b", lambda data: got.append(("b", data)), "/odom")
    spinner, waits = None, None

    def two_samples_at_once():
        a.queue.extend([b"1", b"2"])

    def b_comes():
        spinner.watch(b)
        b.queue.append(b"3")

    def a_goes():
        spinner.unwatch(a)
        a.queue.append(b"last")  # already waiting: taken, as rclpy destroys a once it is let go

    def after_a():
        a.handle.destroyed = True
        a.queue.append(b"lost")

    spinner, waits = spinner_world(agent, [two_samples_at_once, b_comes, lambda: None, a_goes, after_a])
    spinner.watch(a)
    spinner.changed.triggered = False
    spinner.run()
    # b's sample waited for the wait set that has b: taken after the list was read again.
    assert got == [("a", b"1"), ("a", b"2"), ("b", b"3"), ("a", b"last")]
    assert waits == [["a"], ["a"], ["a", "b"], ["a", "b"], ["b"], ["b"]]
    assert a.handle.held == b.handle.held == 0


def test_a_callback_that_fails_loses_its_sample_not_the_topic(agent, capsys):
    got = []

    def callback(data):
        if data == b"bad":
            raise ValueError("no")
        got.append(data)
    sub = Sub("a", callback)
    spinner, _ = spinner_world(agent, [lambda: sub.queue.extend([b"bad", b"good"]), lambda: sub.queue.append(b"next")])
    spinner.watch(sub)
    spinner.run()
    assert got == [b"good", b"next"]
    assert "/chatter: dropped a sample: ValueError: no" in capsys.readouterr().err


def test_a_subscription_destroyed_before_the_spinner_holds_it_is_passed_over(agent):
    sub = Sub("a", lambda data: None)
    sub.handle.destroyed = True  # the main loop destroyed it between watch() and the wait
    spinner, waits = spinner_world(agent, [])
    spinner.watch(sub)
    attempts = []
    real_spin = spinner.spin

    def spin(context, subs):
        attempts.append(list(subs))
        if len(attempts) == 2:
            spinner.unwatch(sub)
        return real_spin(context, subs)
    spinner.spin = spin
    spinner.run()
    assert attempts == [[sub], [sub], []] and waits == [[]]


# -- the workspace's interface packages (relay_interfaces.py WorkspaceInterfaces) -------------------

GENUINE = "X = 'genuine'\n"


def _interfaces(agent, monkeypatch, tmp_path, files: dict[str, str], listed: dict[str, list[str]] | None = None):
    """An install space at tmp_path with `files` (relative to its site directory) and the build's
    list naming `listed` (package -> those of its files; default: all of them), the relay's finder
    on it, restored after the test as the import system was."""
    import hashlib

    site = tmp_path / "lib" / "python3.11" / "site-packages"
    for rel, text in files.items():
        (site / rel).parent.mkdir(parents=True, exist_ok=True)
        (site / rel).write_text(text)
    if listed is None:
        listed = {}
        for rel in files:
            listed.setdefault(rel.split("/", 1)[0], []).append(rel)
    manifest = {"site": "lib/python3.11/site-packages", "packages": {
        pkg: {f"lib/python3.11/site-packages/{rel}": hashlib.sha256((site / rel).read_bytes()).hexdigest() for rel in rels}
        for pkg, rels in listed.items()}}
    (tmp_path / "share" / "ccrp").mkdir(parents=True)
    (tmp_path / "share" / "ccrp" / "interfaces.json").write_text(json.dumps(manifest))
    monkeypatch.setattr(agent.interfaces.WorkspaceInterfaces, "ROOT", str(tmp_path))
    monkeypatch.setattr(agent.interfaces.WorkspaceInterfaces, "_installed", None)
    for pkg in {rel.split("/", 1)[0] for rel in files}:
        for mod in [m for m in sys.modules if m == pkg or m.startswith(pkg + ".")]:
            monkeypatch.delitem(sys.modules, mod)
    logged = []
    monkeypatch.setattr(agent.interfaces, "log", logged.append)
    return site, logged


def test_the_relay_loads_a_workspace_message_as_ccrps_build_listed_it(agent, monkeypatch, tmp_path):
    site, logged = _interfaces(agent, monkeypatch, tmp_path, {
        "my_msgs/__init__.py": GENUINE, "my_msgs/msg/__init__.py": "from my_msgs.msg._num import Num\n",
        "my_msgs/msg/_num.py": "class Num:\n    pass\n"})
    cls = agent.message_class("my_msgs/msg/Num")
    assert cls.__name__ == "Num" and sys.modules["my_msgs"].__file__ == str(site / "my_msgs" / "__init__.py")
    assert logged == [f"workspace interfaces: my_msgs loaded from {site / 'my_msgs'}"]
    # The distro's own package wins over one of the same name in the workspace (the finder is last).
    assert agent.message_class("std_msgs/msg/String") is String


@pytest.mark.parametrize("change, why", [
    # An ament_python package of the workspace put a module beside the generated ones: an
    # extension module is imported before the .py of the same name.
    (lambda site: (site / "my_msgs" / "msg" / "_num.cpython-311-x86_64-linux-gnu.so").write_text("x"),
     "_num.cpython-311-x86_64-linux-gnu.so was not generated by ccrp's build"),
    (lambda site: (site / "my_msgs" / "msg" / "_num.py").write_text("import os; os.system('id')\n"),
     "_num.py is not the file ccrp's build generated"),
    (lambda site: (site / "my_msgs" / "msg" / "_num.py").unlink(), "_num.py is not the file ccrp's build generated"),
])
def test_a_workspace_message_package_not_as_built_is_refused_whole(agent, monkeypatch, tmp_path, change, why):
    site, logged = _interfaces(agent, monkeypatch, tmp_path, {
        "my_msgs/__init__.py": GENUINE, "my_msgs/msg/__init__.py": "from my_msgs.msg._num import Num\n",
        "my_msgs/msg/_num.py": "class Num:\n    pass\n"})
    change(site)
    with pytest.raises(ImportError):
        agent.message_class("my_msgs/msg/Num")
    assert len(logged) == 1 and logged[0].startswith("workspace interfaces: my_msgs not loaded: ") and why in logged[0], logged
    assert "my_msgs" not in sys.modules


def test_workspace_code_the_build_did_not_list_is_never_imported(agent, monkeypatch, tmp_path):
    """A Python package of the workspace named as a peer's type would name it (mapper/msg/X): not
    an interface package, never imported by the relay; nor a listed file outside the package."""
    site, logged = _interfaces(agent, monkeypatch, tmp_path, {
        "my_msgs/__init__.py": GENUINE, "mapper/__init__.py": "raise SystemExit('workspace code ran')\n",
        "mapper/msg.py": "X = 1\n"}, listed={"my_msgs": ["my_msgs/__init__.py", "mapper/__init__.py"]})
    for name in ("mapper/msg/X", "my_msgs/msg/X"):
        with pytest.raises(ImportError):
            agent.message_class(name)
    assert logged == [f"workspace interfaces: my_msgs not loaded: the build's list names {site / 'mapper' / '__init__.py'}"]


def test_a_pyc_beside_a_workspace_message_is_never_run(agent, monkeypatch, tmp_path):
    """Bytecode in the package's __pycache__, made to match the checked source's size and time (as
    Python's check goes), is not what runs: the relay reads no bytecode there."""
    import importlib.util
    import os
    import py_compile

    site, _ = _interfaces(agent, monkeypatch, tmp_path, {"my_msgs/__init__.py": GENUINE, "my_msgs/msg/__init__.py": "class Num:\n    pass\n"})
    genuine = site / "my_msgs" / "__init__.py"
    evil = tmp_path / "evil.py"
    evil.write_text(GENUINE.replace("genuine", "evilevi"))
    stat = genuine.stat()
    os.utime(evil, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    py_compile.compile(str(evil), cfile=importlib.util.cache_from_source(str(genuine)), dfile=str(genuine))
    agent.message_class("my_msgs/msg/Num")
    assert sys.modules["my_msgs"].X == "genuine"
