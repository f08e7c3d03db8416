#!/usr/bin/python3
"""ccrp relay agent: runs ON a clone (system python3 + zenoh + rospy, or on a ROS 2 clone rclpy
from the distro's venv, which ros-run puts on the path; nothing from ccrp).

ROS 1 (the environment names a master):
Exports: subscribes to this clone's exported ROS topics as rospy.AnyMsg (raw bytes, any type,
no generated code) and puts each message on Zenoh key ccrp/<fleet>/<robot>/<topic> with its
type, md5sum, definition and a sequence number in the attachment.
Imports: subscribes to the Zenoh keys of the topics this clone imports and republishes each as
/<source><topic> with a message class made at run time from the type, md5sum and definition.

ROS 2 (no master; docs/ros2.md): the same agent with relay_ros2.py beside it (rclpy): exports and
imports carry serialized CDR with the type name and reliability/durability QoS.

Peers are listed explicitly (no scouting) and reached over mutual TLS with certificates from the
fleet's relay CA, each admitted by its certificate's CN (Zenoh access control). The config file is
re-read when it changes, so a fleet change adds or drops imports without a restart; Zenoh re-dials
a listed peer whose clone restarted. The agent writes its view (peers connected, messages relayed,
gaps seen) to a status file every second for `ccrp status`.
"""

from __future__ import annotations

import json
import os
import queue
import secrets
import sys
import threading
import time

import zenoh

try:
    import rosgraph
    import rospy
except ImportError:  # a ROS 2 clone: rclpy instead (relay_ros2.py)
    rosgraph = rospy = None

DEFAULT_CONFIG = "/etc/ccrp/relay.json"
NOBODY = "no partner (ccrp)"  # relay certificates are named relay-<robot>-<n>
# How long a new ROS publisher waits for the subscribers the master knows to connect before it
# sends its first message (otherwise that message would go to nobody).
CONNECT_GRACE = 2.0


def log(msg: str) -> None:
    print(f"ccrp-relay: {msg}", file=sys.stderr, flush=True)


def session_id(stable: str) -> str:
    """This session's Zenoh id: the clone's stable part (sharing.zenoh_id) and 8 random hex digits.
    With the stable id alone, a session opened again (a new peer list) was the same peer to the
    others as the one it replaced: a partner still holding that one's link refused the new one, or
    dropped the new one's subscriptions with the old link's (seen: a partner not dialled again
    within 20 s; puts never reaching a clone whose subscriber the partner had dropped)."""
    return stable + secrets.token_hex(4)


def connected_peers(session, peers: dict) -> dict[str, bool]:
    """Peer name -> whether a session of its clone is linked to ours (by the id's stable part)."""
    ids = [str(z) for z in session.info.peers_zid()] if session else []
    return {name: any(z.startswith(p["id"]) for z in ids) for name, p in peers.items()}


def zenoh_config(cfg: dict) -> "zenoh.Config":
    c = zenoh.Config()
    c.insert_json5("id", json.dumps(session_id(cfg["id"])))
    c.insert_json5("mode", '"peer"')
    # Clouds have no multicast; peers come from the config only.
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([cfg["listen"]]))
    c.insert_json5("connect/endpoints", json.dumps(sorted(p["endpoint"] for p in cfg["peers"].values())))
    tls = cfg["tls"]
    c.insert_json5("transport/link/tls", json.dumps({
        "root_ca_certificate": tls["ca"], "enable_mtls": True,
        "listen_private_key": tls["key"], "listen_certificate": tls["cert"],
        "connect_private_key": tls["key"], "connect_certificate": tls["cert"],
    }))
    # Only the fleet's current partner clones may exchange anything: admitted by the CN of their
    # relay certificate (one per certificate issued), so a replaced or revoked one gets nothing.
    # Zenoh wants every list non-empty; with no partner, a CN that no certificate carries.
    cns = sorted(p["cn"] for p in cfg["peers"].values()) or [NOBODY]
    c.insert_json5("access_control", json.dumps({
        "enabled": True, "default_permission": "deny",
        "rules": [{"id": "fleet", "permission": "allow", "flows": ["ingress", "egress"],
                   "messages": ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                                "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"],
                   "key_exprs": [f"ccrp/{cfg['fleet']}/**"]}],
        "subjects": [{"id": "partners", "cert_common_names": cns}],
        "policies": [{"rules": ["fleet"], "subjects": ["partners"]}],
    }))
    return c


def congestion(reliable: bool) -> "zenoh.CongestionControl":
    """How an export's Zenoh publisher meets a full queue towards a peer. Zenoh's default (DROP)
    drops a sample that waits there over 1 ms, which a loaded host reaches: measured here, the
    importing agents counted 12 (Noetic) and 68 (Jazzy) missing sequence numbers in one
    `bench/relay.py` run beside other work. A reliable topic (every ROS 1 topic, TCP; a ROS 2 one
    offered RELIABLE) is then relayed as it is delivered at home: the put waits for room (BLOCK),
    and the backlog stays in the topic's own queue (rospy's queue_size, the DDS history), which
    drops its oldest when full as it would for a slow subscriber. A best-effort one keeps DROP."""
    return zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP


def links(cfg: dict) -> list[tuple[str, str]]:
    """What a session is opened for: the peers' endpoints and the CNs admitted."""
    return sorted((p["endpoint"], p["cn"]) for p in cfg["peers"].values())


def raw_class(msg_type: str, md5: str, definition: str):
    """A message class that publishes pre-serialized bytes under a given type."""
    return type(
        "Raw_" + msg_type.replace("/", "_"), (rospy.AnyMsg,),
        {"_type": msg_type, "_md5sum": md5, "_full_text": definition, "_has_header": False, "__slots__": ()},
    )


class Export:
    def __init__(self, relay: "Relay", topic: str) -> None:
        self.topic, self.count = topic, 0
        self.publisher = relay.session.declare_publisher(relay.key(relay.cfg["robot"], topic),
                                                         congestion_control=congestion(reliable=True))
        self.sub = rospy.Subscriber(topic, rospy.AnyMsg, self.forward, queue_size=100, tcp_nodelay=True)

    def forward(self, msg) -> None:
        header = msg._connection_header
        self.count += 1
        meta = {"t": header["type"], "m": header["md5sum"], "d": header.get("message_definition", ""), "s": self.count}
        self.publisher.put(bytes(msg._buff), attachment=json.dumps(meta).encode())

    def close(self) -> None:
        self.sub.unregister()
        self.publisher.undeclare()


class Import:
    """One imported topic: Zenoh samples queued in order, republished by one thread."""

    def __init__(self, relay: "Relay", source: str, topic: str, local: str) -> None:
        self.relay, self.local, self.count, self.gaps, self.last_seq = relay, local, 0, 0, 0
        self.pub = None
        self.queue: queue.Queue = queue.Queue(maxsize=1000)
        self.thread = threading.Thread(target=self.run, name=f"import {local}", daemon=True)
        self.thread.start()
        self.sub = relay.session.declare_subscriber(relay.key(source, topic), self.queue.put)

    def _publisher(self, meta: dict):
        if self.pub is None or self.pub.data_class._md5sum != meta["m"]:
            if self.pub is not None:
                self.pub.unregister()
            self.pub = rospy.Publisher(self.local, raw_class(meta["t"], meta["m"], meta["d"]), queue_size=100,
                                       tcp_nodelay=True)
            self._await_subscribers()
        return self.pub

    def _await_subscribers(self) -> None:
        try:
            subs = {t: n for t, n in rosgraph.Master("/ccrp_relay").getSystemState()[1]}.get(self.local, [])
        except Exception:  # noqa: BLE001 - the master may be restarting; don't hold the topic up
            return
        deadline = time.monotonic() + CONNECT_GRACE
        while self.pub.get_num_connections() < len(subs) and time.monotonic() < deadline:
            time.sleep(0.02)

    def _publish(self, meta: dict, payload: bytes) -> None:
        msg = self._publisher(meta).data_class()
        msg._buff = payload
        self.pub.publish(msg)

    def run(self) -> None:
        while True:
            sample = self.queue.get()
            if sample is None:
                return
            try:
                meta = json.loads(sample.attachment.to_bytes())
                self._publish(meta, sample.payload.to_bytes())
                if self.last_seq and meta["s"] > self.last_seq + 1:
                    self.gaps += meta["s"] - self.last_seq - 1
                self.last_seq = meta["s"]
                self.count += 1
            except Exception as exc:  # noqa: BLE001 - one bad sample must not stop the topic
                log(f"{self.local}: dropped a sample: {exc}")

    def _close_pub(self) -> None:
        self.pub.unregister()

    def close(self) -> None:
        self.sub.undeclare()
        self.queue.put(None)
        if self.pub is not None:
            self._close_pub()


class Ros1:
    """The rospy side: one node per agent, callbacks on rospy's threads."""

    Export, Import = Export, Import

    def __init__(self) -> None:
        rospy.init_node("ccrp_relay", anonymous=False, disable_signals=True)

    def ok(self) -> bool:
        return not rospy.is_shutdown()


class Relay:
    def __init__(self, cfg: dict, ros) -> None:
        self.cfg, self.ros, self.session, self.endpoints = cfg, ros, None, None
        self.exports: dict[str, Export] = {}
        self.imports: dict[str, Import] = {}
        self.apply(cfg)

    def _open(self, cfg: dict, endpoints: list[str]) -> None:
        """A Zenoh session dials the peers its config names when it opens, and never others: a
        partner added later (a clone that became ready after this one) is only reached through a
        new session. Exports and imports are declared again on it by apply()."""
        for topic in list(self.exports):
            self.exports.pop(topic).close()
        for local in list(self.imports):
            self.imports.pop(local).close()
        if self.session is not None:
            old, self.session = self.session, None
            try:
                old.close()
            except Exception as exc:  # noqa: BLE001 - the new session opens whatever the old one does
                # Zenoh's close can time out on a link to a peer that is gone (a deleted clone):
                # seen here as "close operation timed out", after which the relay had neither its
                # old session nor a new one, and no exports or imports, until the next config.
                log(f"closing the previous session: {type(exc).__name__}: {exc}")
        # If this raises, endpoints stay as they were and the next apply() tries again.
        self.session, self.endpoints = zenoh.open(zenoh_config(cfg)), endpoints

    def key(self, source: str, topic: str) -> str:
        return f"ccrp/{self.cfg['fleet']}/{source}/{topic.strip('/')}"

    def apply(self, cfg: dict) -> None:
        """Bring exports and imports in line with cfg; untouched ones keep running unless the
        peers changed (then the session is opened again, see _open)."""
        endpoints = links(cfg)
        if endpoints != self.endpoints:
            self._open(cfg, endpoints)
        self.cfg = cfg
        want_exports = set(cfg["exports"])
        want_imports = {i["as"]: i for i in cfg["imports"]}
        for topic in set(self.exports) - want_exports:
            self.exports.pop(topic).close()
        for topic in sorted(want_exports - set(self.exports)):
            self.exports[topic] = self.ros.Export(self, topic)
        for local in set(self.imports) - set(want_imports):
            self.imports.pop(local).close()
        for local in sorted(set(want_imports) - set(self.imports)):
            i = want_imports[local]
            self.imports[local] = self.ros.Import(self, i["source"], i["topic"], local)
        log(f"exports {sorted(self.exports)}; imports {sorted(self.imports)}; peers {sorted(cfg['peers'])}")

    def poll(self) -> None:
        """ROS 2: subscribe exported topics whose publishers appeared (or changed) since."""
        for export in self.exports.values():
            if hasattr(export, "poll"):
                export.poll()

    def status(self) -> dict:
        return {
            "time": time.time(),
            "peers": connected_peers(self.session, self.cfg["peers"]),
            "exports": {t: e.count for t, e in self.exports.items()},
            "imports": {t: {"received": i.count, "gaps": i.gaps} for t, i in self.imports.items()},
        }


def write_atomic(path: str, text: str) -> None:
    tmp = f"{path}.tmp"
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


def wait_for_files(cfg: dict) -> None:
    """The clone's TLS files arrive after boot (never in user-data): wait for them."""
    while not all(os.access(cfg["tls"][k], os.R_OK) for k in ("ca", "cert", "key")):
        time.sleep(1)


def main() -> None:
    path = sys.argv[1] if len(sys.argv) > 1 else DEFAULT_CONFIG
    while not os.path.exists(path):
        time.sleep(1)
    mtime = os.stat(path).st_mtime
    with open(path) as fh:
        cfg = json.load(fh)
    wait_for_files(cfg)
    # A ROS 1 clone's environment names its master (ros.env); a ROS 2 clone's has none, and has
    # relay_ros2.py beside this file (a bare cloud clone's user-data carries this one: kept small).
    if os.environ.get("ROS_MASTER_URI"):
        ros = Ros1()
    else:
        from relay_ros2 import Ros2

        ros = Ros2()
    relay = Relay(cfg, ros)
    log(f"{cfg['robot']}: listening on {cfg['listen']}")
    while ros.ok():
        try:
            relay.poll()
            changed = os.stat(path).st_mtime
            if changed != mtime:
                with open(path) as fh:
                    relay.apply(json.load(fh))
                mtime = changed  # only once applied: a config that failed is applied again next second
            write_atomic(cfg["status"], json.dumps(relay.status()))
        except Exception as exc:  # noqa: BLE001 - keep relaying; report and retry next second
            log(f"{type(exc).__name__}: {exc}")
        time.sleep(1)


if __name__ == "__main__":
    main()
