"""The relay agent's ROS 2 side (rclpy), imported by relay.py on a clone whose ROS environment
names no master (docs/ros2.md, Topic sharing between Jazzy clones). Runs on Debian's python3 with
the distro's venv on its path (ros-run); nothing from ccrp.

Exports: an exported topic is subscribed once a publisher of it is on the graph, with its type and
its publishers' reliability and durability, as serialized CDR (raw); the Zenoh attachment carries
the type name, that QoS and the sequence number. Imports: the bytes are published as they came on
/<source><topic>, with that type (its generated class, from the wheels) and that QoS.
"""

from __future__ import annotations

import contextlib
import importlib
import ipaddress
import json
import os
import re
import tempfile
import threading
import time

from relay import CONNECT_GRACE, Import, congestion, log, write_atomic

RELIABILITY = ("reliable", "best_effort")
DURABILITY = ("transient_local", "volatile")


def message_type(name: str) -> tuple[str, str]:
    """(package, type) of a ROS 2 message type name, pkg/msg/Type as the graph gives it (or
    pkg/Type). Anything else is refused: the name comes from the graph or from a peer and is
    imported as a module."""
    parts = name.split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    ident = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")
    if len(parts) != 3 or parts[1] != "msg" or not ident.match(parts[0]) or not ident.match(parts[2]):
        raise ValueError(f"not a message type: {name!r}")
    return parts[0], parts[2]


def message_class(name: str):
    """The generated class of a message type (the distro's wheels have no rosidl_runtime_py): the
    distro's, else one of the workspace's interface packages (relay_interfaces.py, which `fleet up`
    pushes beside this file: a bare clone's user-data has no room for it, nor use)."""
    package, kind = message_type(name)
    try:
        import relay_interfaces
    except ImportError:
        pass
    else:
        relay_interfaces.WorkspaceInterfaces.install()
    return getattr(importlib.import_module(f"{package}.msg"), kind)


def combined_qos(offered: list[tuple[str, str]]) -> dict:
    """The reliability and durability to take for a topic's publishers [(reliability, durability)
    as lower-case policy names]: the weakest of them, which a subscription must ask for no more
    than to match every publisher (a reliable one would miss a best-effort publisher), and what
    the importing clone's publisher then offers."""
    if not offered:
        raise ValueError("no publishers")
    reliable = all(r == "reliable" for r, _ in offered)
    lasting = all(d == "transient_local" for _, d in offered)
    return {"reliability": "reliable" if reliable else "best_effort",
            "durability": "transient_local" if lasting else "volatile"}


def qos_profile(qos: dict, depth: int = 100):
    """An rclpy QoSProfile from combined_qos's names; a name not known is refused."""
    if qos.get("reliability") not in RELIABILITY or qos.get("durability") not in DURABILITY:
        raise ValueError(f"unknown QoS {qos!r}")
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=depth, reliability=ReliabilityPolicy[qos["reliability"].upper()],
                      durability=DurabilityPolicy[qos["durability"].upper()])


def offered_qos(infos) -> list[tuple[str, str]]:
    """(reliability, durability) names of the publishers rclpy's graph lists (TopicEndpointInfo)."""
    return [(i.qos_profile.reliability.name.lower(), i.qos_profile.durability.name.lower()) for i in infos]


class Export2:
    """An exported ROS 2 topic. There is no `any type` subscription in ROS 2: it is subscribed once
    a publisher of it is on the graph (poll, every second), and again if its type or its
    publishers' QoS change."""

    def __init__(self, relay, topic: str) -> None:  # relay: relay.Relay
        self.relay, self.topic, self.count = relay, topic, 0
        self.sub, self.meta, self.refused, self.publisher = None, None, None, None
        self.poll()

    def poll(self) -> None:
        node = self.relay.ros.node
        infos = node.get_publishers_info_by_topic(self.topic)
        if not infos:
            return
        types = sorted({i.topic_type for i in infos})
        if len(types) > 1:
            log(f"{self.topic}: published with several types {types}: relaying {types[0]}")
        infos = [i for i in infos if i.topic_type == types[0]]
        meta = {"t": types[0], "q": combined_qos(offered_qos(infos))}
        if meta in (self.meta, self.refused):
            return
        try:
            cls, qos = message_class(meta["t"]), qos_profile(meta["q"])
        except (ImportError, AttributeError, ValueError) as exc:
            self.refused = meta  # said once, not every second; a change of type tries again
            log(f"{self.topic}: cannot relay {meta['t']}: {exc}")
            return
        if self.sub is not None:
            self.relay.ros.unwatch(self.sub)
            node.destroy_subscription(self.sub)
            self.sub = None
        reliable = meta["q"]["reliability"] == "reliable"
        if self.meta is None or reliable != (self.meta["q"]["reliability"] == "reliable"):
            # The Zenoh publisher follows the topic's reliability (relay.congestion).
            if self.publisher is not None:
                self.publisher.undeclare()
            self.publisher = self.relay.session.declare_publisher(
                self.relay.key(self.relay.cfg["robot"], self.topic), congestion_control=congestion(reliable))
        self.sub = node.create_subscription(cls, self.topic, self.forward, qos, raw=True)
        self.relay.ros.watch(self.sub)
        self.meta = meta
        log(f"{self.topic}: exporting {meta['t']} ({meta['q']['reliability']}, {meta['q']['durability']})")

    def forward(self, data: bytes) -> None:
        self.count += 1
        self.publisher.put(bytes(data), attachment=json.dumps({**self.meta, "s": self.count}).encode())

    def close(self) -> None:
        if self.sub is not None:
            self.relay.ros.unwatch(self.sub)
            self.relay.ros.node.destroy_subscription(self.sub)
        if self.publisher is not None:
            self.publisher.undeclare()


class Import2(Import):
    """An imported ROS 2 topic: the serialized bytes published as they came (rclpy publishes bytes
    raw), by a publisher of the sample's type and QoS."""

    kind = None

    def _publish(self, meta: dict, payload: bytes) -> None:
        kind = (meta["t"], meta["q"]["reliability"], meta["q"]["durability"])
        node = self.relay.ros.node
        if self.pub is None or kind != self.kind:
            cls, qos = message_class(meta["t"]), qos_profile(meta["q"])  # a bad sample changes nothing
            if self.pub is not None:
                node.destroy_publisher(self.pub)
                self.pub = None
            self.pub = node.create_publisher(cls, self.local, qos)
            self.kind = kind
            # As for ROS 1: subscribers the graph knows get the first message too, once matched.
            deadline = time.monotonic() + CONNECT_GRACE
            while self.pub.get_subscription_count() < node.count_subscribers(self.local) and \
                    time.monotonic() < deadline:
                time.sleep(0.02)
        self.pub.publish(payload)

    def _close_pub(self) -> None:
        self.relay.ros.node.destroy_publisher(self.pub)


# Fast DDS delivers between processes of one host through shared memory, where a writer puts its
# samples in a segment the reader created with its umask (0644): a writer of another user cannot,
# and the relay runs as its own user. rmw_fastrtps sets that transport itself under
# ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, so the agent's participant takes this profile instead
# (range SYSTEM_DEFAULT: the middleware's settings as given): UDP only, the same unicast discovery
# as LOCALHOST + ROS_STATIC_PEERS (this host and the robot's VPN address), no multicast.
# Its sockets take up to RECEIVE_BUFFER bytes: a sample over 64 KB comes as several datagrams at
# once (a 320x240 image as four), and the kernel's default 208 KB dropped the last of them often
# enough that the sample waited for a NACK and its repair (measured here: p50/p95 2.3/17.9 ms for
# such an image from a node to the agent, 1.4/1.8 ms with 2 MB). The kernel caps it at
# net.core.rmem_max (doubled), which Fast DDS accepts.
# The same overflow happens in the socket of a subscriber on the importing clone, which belongs to
# the user's node and keeps the kernel's 208 KB (rmw_fastrtps makes its own UDP transport under
# LOCALHOST, and net.core.rmem_default is not per network namespace: Docker refuses it as a
# container sysctl). A fragment lost there is repaired when the reader NACKs it; a writer's default
# wait of 5 ms before it answers a NACK (nackResponseDelay) is waiting for nothing here, so the
# agent's writers answer at once (measured: docs/ros2.md, The relay's speed).
RECEIVE_BUFFER = 2 * 1024 * 1024
FASTDDS_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>ccrp_udp</transport_id>
      <type>UDPv4</type>
      <maxInitialPeersRange>32</maxInitialPeersRange>
      <receiveBufferSize>{receive_buffer}</receiveBufferSize>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="ccrp_relay" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>ccrp_udp</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
      <builtin>
        <metatrafficUnicastLocatorList><locator><udpv4><address>0.0.0.0</address></udpv4></locator></metatrafficUnicastLocatorList>
        <initialPeersList>
{peers}
        </initialPeersList>
      </builtin>
    </rtps>
  </participant>
  <data_writer profile_name="ccrp_relay_writer" is_default_profile="true">
    <times><nackResponseDelay><sec>0</sec><nanosec>0</nanosec></nackResponseDelay></times>
  </data_writer>
</profiles>
"""


def fastdds_profile(static_peers: str) -> str:
    """The agent's Fast DDS profile for ROS_STATIC_PEERS (';'-separated); only IPv4 addresses are
    taken (ccrp writes the robot's VPN address there)."""
    peers = ["127.0.0.1"]
    for peer in filter(None, (p.strip() for p in static_peers.split(";"))):
        try:
            peers.append(str(ipaddress.IPv4Address(peer)))
        except ValueError:
            log(f"ROS_STATIC_PEERS: {peer!r} is not an IPv4 address: left out")
    return FASTDDS_PROFILE.format(receive_buffer=RECEIVE_BUFFER, peers="\n".join(
        f"          <locator><udpv4><address>{p}</address></udpv4></locator>" for p in dict.fromkeys(peers)))


class Spinner:
    """Takes the exported topics' samples and calls their callbacks, on one thread, instead of an
    rclpy executor: the executor builds a new wait set, a task and a coroutine per sample, which
    cost 0.78 ms of CPU per sample here against 0.27 ms for this loop (docs/ros2.md, The relay's
    speed). The wait set is built again only when a subscription comes or goes (`changed`).
    Entity changes stay with the agent's main loop: it destroys a subscription after unwatch(), and
    rclpy defers that until this thread lets go of its handle."""

    def __init__(self, node, rclpy_impl, invalid_handle: type[Exception]) -> None:
        self.node, self._rclpy, self.invalid = node, rclpy_impl, invalid_handle
        self.subs: list = []
        self.lock = threading.Lock()
        self.changed = node.create_guard_condition(lambda: None)

    def watch(self, sub) -> None:
        with self.lock:
            self.subs.append(sub)
        self.changed.trigger()

    def unwatch(self, sub) -> None:
        with self.lock:
            if sub in self.subs:
                self.subs.remove(sub)
        self.changed.trigger()

    def run(self) -> None:
        context = self.node.context
        while context.ok():
            with self.lock:
                subs = list(self.subs)
            try:
                self.spin(context, subs)
            except self.invalid:  # one of them went meanwhile: take the list again
                continue
            except Exception as exc:  # noqa: BLE001 - rclpy shutting down, or a bug: say it, go on
                if context.ok():
                    log(f"spinner: {type(exc).__name__}: {exc}")
                    time.sleep(1)

    def spin(self, context, subs: list) -> None:
        """Wait on subs until the list changes."""
        with contextlib.ExitStack() as held:
            held.enter_context(context.handle)
            held.enter_context(self.changed.handle)
            for sub in subs:
                held.enter_context(sub.handle)
            wait_set = self._rclpy.WaitSet(len(subs), 1, 0, 0, 0, 0, context.handle)
            while context.ok():
                wait_set.clear_entities()
                for sub in subs:
                    wait_set.add_subscription(sub.handle)
                wait_set.add_guard_condition(self.changed.handle)
                wait_set.wait(1_000_000_000)
                ready = wait_set.get_ready_entities("subscription")
                for sub in subs:
                    if sub.handle.pointer in ready:
                        self.take(sub)
                if wait_set.get_ready_entities("guard_condition"):
                    return

    def take(self, sub) -> None:
        """Every sample waiting (a wake-up may stand for several)."""
        while True:
            taken = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return
            try:
                sub.callback(taken[0])
            except Exception as exc:  # noqa: BLE001 - one bad sample must not stop the topic
                log(f"{sub.topic_name}: dropped a sample: {type(exc).__name__}: {exc}")


class Ros2:
    """The rclpy side: one node, whose exported topics' samples a Spinner thread takes; graph
    queries and entity changes come from the agent's main loop, which rclpy allows meanwhile."""

    Export, Import = Export2, Import2

    def __init__(self) -> None:
        run = os.environ.get("RUNTIME_DIRECTORY") or tempfile.mkdtemp(prefix="ccrp-relay-")
        profile = os.path.join(run.split(":")[0], "fastdds.xml")
        write_atomic(profile, fastdds_profile(os.environ.pop("ROS_STATIC_PEERS", "")))
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = profile
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"

        import rclpy
        from rclpy.exceptions import InvalidHandle
        from rclpy.impl.implementation_singleton import rclpy_implementation
        from rclpy.parameter import Parameter

        from rclpy.signals import SignalHandlerOptions

        self.rclpy = rclpy
        # No rclpy signal handlers: SIGTERM (systemctl stop) ends the agent at once, as on ROS 1
        # (rospy's disable_signals). With them, the main loop ended while the spinner thread still
        # waited in rcl, and systemd waited its 90 s stop timeout before killing the agent.
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        # Nothing asks the agent's node for parameters, its type descriptions or its log: without
        # those services and /rosout it has no DDS endpoints beyond the relayed topics.
        self.node = rclpy.create_node(
            "ccrp_relay", start_parameter_services=False, enable_rosout=False,
            parameter_overrides=[Parameter("start_type_description_service", value=False)])
        self.spinner = Spinner(self.node, rclpy_implementation, InvalidHandle)
        self.watch, self.unwatch = self.spinner.watch, self.spinner.unwatch
        threading.Thread(target=self.spinner.run, name="rclpy", daemon=True).start()

    def ok(self) -> bool:
        return self.rclpy.ok()
