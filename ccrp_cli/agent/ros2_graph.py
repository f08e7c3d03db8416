"""The ROS 2 graph as a clone sees it, printed as one JSON object: what `ccrp status` shows in place
of a ROS 1 master (agent/health.py runs it). Run on the clone with the distro's python, in the
clone's ROS environment (/etc/ccrp/ros.env: its robot's domain, LOCALHOST, the robot as static peer):

  python ros2_graph.py serve PATH  keep one node in the graph and tell what it sees to whoever
                                   connects to the Unix socket PATH (ccrp-graph.service; health.py)
  python ros2_graph.py [SECONDS]   the nodes and published topics seen within SECONDS (default 3), by
                                   a node of its own (a clone without ccrp-graph.service)
  python ros2_graph.py check       exit 0 once a node could be created (the RMW loads and starts)

A node is `remote` when its participant runs on another host: DDS GUID prefixes carry a host id
(bytes 2-3 in Fast DDS), and the clone's only DDS peer is its robot, so a remote node is the robot's.

After the robot's participant was lost and found again (its tunnel down for longer than the DDS
lease: the entry gateway made again, measured on the real OpenStack), a long-lived node saw the
robot's endpoints again but never its node names again: they stayed _NODE_NAME_UNKNOWN_ (the
graph's names come from ros_discovery_info, which it did not get again). A fresh participant
names them at once, so the keeper starts a fresh one when a remote node's name stays unknown
(RENEW_AFTER), at most once a RENEW_EVERY. Only a remote one: a local node may show unknown for as
long as it runs (seen on Docker clones), and a fresh participant would not name it either.
"""

import json
import os
import sys
import time


def main():
    import rclpy

    rclpy.init()
    node = rclpy.create_node("ccrp_graph")
    try:
        if sys.argv[1:2] == ["serve"] and len(sys.argv) == 3:
            node = serve(node, sys.argv[2])
            return
        if sys.argv[1:] == ["check"]:
            print(json.dumps({"ok": True}))
            return
        wait = float(sys.argv[1]) if len(sys.argv) > 1 else 3.0
        # Our own host id: from our /rosout publisher's GUID (every rclpy/rclcpp node has one).
        mine = None
        end = time.monotonic() + wait
        seen_remote_at = None
        nodes, topics = {}, []
        while time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.1)
            nodes, topics, mine, _ = graph(node, mine)
            if seen_remote_at is None and "remote" in nodes.values():
                seen_remote_at = time.monotonic()
            # Once the robot's participant is there, its endpoints come within moments.
            if seen_remote_at is not None and time.monotonic() - seen_remote_at > 0.5:
                break
        print(json.dumps({"reachable": True, "nodes": nodes, "published_topics": topics}))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


UNKNOWN = "_NODE_NAME_UNKNOWN_"
RENEW_AFTER = 10.0  # seconds a remote node's name may stay unknown before the keeper starts a fresh participant
RENEW_EVERY = 60.0  # and not again sooner, whatever it then sees


def renew(node):
    """A fresh node in a fresh context (a new DDS participant, which learns every name again)."""
    import rclpy

    node.destroy_node()
    rclpy.try_shutdown()
    rclpy.init()
    return rclpy.create_node("ccrp_graph")


def serve(node, path):
    """Answer each connection to the Unix socket `path` with the graph as this node sees it then,
    one JSON object; returns the node it ends with. Why a service: a node of its own per `ccrp
    status` cost a Python start with rclpy and a DDS discovery round with the robot each time (18 s
    of CPU on an emulated VM, 3 s of waiting anywhere); this node stays in the graph, and costs
    nothing between questions (a graph written every second instead took 12% of an emulated CPU)."""
    import socket

    import rclpy

    mine = None
    unknown_since, renewed_at = None, float("-inf")
    if os.path.lexists(path):
        os.unlink(path)  # the last run's (the directory is systemd's, this user's alone)
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(path)
        server.listen(8)
        server.settimeout(1.0)  # to see rclpy's SIGTERM handler shut the context down (systemctl stop)
        while rclpy.ok():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            with conn:
                try:
                    nodes, topics, mine, lost = graph(node, mine)
                except Exception:
                    if not rclpy.ok():
                        return node
                    raise
                now = time.monotonic()
                if lost:
                    unknown_since = unknown_since or now
                    if now - unknown_since > RENEW_AFTER and now - renewed_at > RENEW_EVERY:
                        # This answer as it is; the next one from the fresh participant.
                        print(f"ccrp-graph: a remote node's name unknown for {RENEW_AFTER:.0f} s: a fresh participant",
                              file=sys.stderr, flush=True)
                        node, mine, unknown_since, renewed_at = renew(node), None, None, now
                else:
                    unknown_since = None
                try:
                    conn.sendall(json.dumps({"reachable": True, "nodes": nodes, "published_topics": topics}).encode())
                except OSError:
                    pass  # the asker left (health.py's timeout): the next one is answered all the same
    return node


def graph(node, mine):
    """({node name: local | remote}, published topics, our host id, whether a remote node's name is
    unknown). A node whose name the graph does not know is left out of the names."""
    hosts = {}
    unknown = set()
    published = set()
    for topic, _types in node.get_topic_names_and_types():
        for kind, infos in (("pub", node.get_publishers_info_by_topic(topic)),
                            ("sub", node.get_subscriptions_info_by_topic(topic))):
            for info in infos:
                name = info.node_namespace.rstrip("/") + "/" + info.node_name
                host = bytes(info.endpoint_gid[2:4])
                if name == "/ccrp_graph":
                    mine = host
                    continue
                if UNKNOWN in name:
                    unknown.add(host)
                else:
                    hosts[name] = host
                if kind == "pub":
                    published.add(topic)
    # Placed by their endpoints: a node without any is not listed (every rclpy/rclcpp node has /rosout).
    nodes = {n: ("local" if mine is not None and h == mine else "remote") for n, h in hosts.items()}
    return nodes, sorted(published), mine, mine is not None and bool(unknown - {mine})


if __name__ == "__main__":
    main()
