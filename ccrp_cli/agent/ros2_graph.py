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
            serve(node, sys.argv[2])
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
            nodes, topics, mine = graph(node, mine)
            if seen_remote_at is None and "remote" in nodes.values():
                seen_remote_at = time.monotonic()
            # Once the robot's participant is there, its endpoints come within moments.
            if seen_remote_at is not None and time.monotonic() - seen_remote_at > 0.5:
                break
        print(json.dumps({"reachable": True, "nodes": nodes, "published_topics": topics}))
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def serve(node, path):
    """Answer each connection to the Unix socket `path` with the graph as this node sees it then,
    one JSON object. Why a service: a node of its own per `ccrp status` cost a Python start with
    rclpy and a DDS discovery round with the robot each time (18 s of CPU on an emulated VM, 3 s of
    waiting anywhere); this node stays in the graph, and costs nothing between questions (a graph
    written every second instead took 12% of an emulated CPU)."""
    import socket

    import rclpy

    mine = None
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
                    nodes, topics, mine = graph(node, mine)
                except Exception:
                    if not rclpy.ok():
                        return
                    raise
                try:
                    conn.sendall(json.dumps({"reachable": True, "nodes": nodes, "published_topics": topics}).encode())
                except OSError:
                    pass  # the asker left (health.py's timeout): the next one is answered all the same


def graph(node, mine):
    """({node name: local | remote}, published topics, our host id)."""
    hosts = {}
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
                hosts[name] = host
                if kind == "pub":
                    published.add(topic)
    # Placed by their endpoints: a node without any is not listed (every rclpy/rclcpp node has /rosout).
    nodes = {n: ("local" if mine is not None and h == mine else "remote") for n, h in hosts.items()}
    return nodes, sorted(published), mine


if __name__ == "__main__":
    main()
