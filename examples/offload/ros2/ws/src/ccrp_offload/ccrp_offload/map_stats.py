"""Print the map summaries a clone receives (ccrp_offload_msgs/MapStats, the workspace's own
message) as JSON lines: its own mapper's /map_stats, or another robot's, imported through ccrp's
topic sharing as /<robot>/map_stats. With --service, ask a mapper's /last_map instead.

Run on a clone, in the workspace's environment:
  /usr/local/lib/ccrp/ros-run env CCRP_WORKSPACE=1 ... (see examples/offload/README.md)
  python3 -m ccrp_offload.map_stats /nao1/map_stats -n 1 --timeout 60
Exits 0 once it printed -n of them, 1 if the time ran out first."""
import argparse
import json
import sys
import time

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from ccrp_offload_msgs.msg import MapStats
from ccrp_offload_msgs.srv import LastMap


def as_dict(m: MapStats) -> dict:
    return {"robot": m.robot, "version": m.version, "width": m.width, "height": m.height,
            "occupied": m.occupied, "free": m.free, "frame": m.header.frame_id}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("topic", nargs="?", default="/map_stats")
    ap.add_argument("-n", type=int, default=1, help="how many to print")
    ap.add_argument("--timeout", type=float, default=30.0)
    ap.add_argument("--service", help="a LastMap service to call instead, e.g. /last_map")
    args = ap.parse_args(argv)
    rclpy.init()
    node = rclpy.create_node("map_stats")
    got = []
    try:
        deadline = time.monotonic() + args.timeout
        if args.service:
            client = node.create_client(LastMap, args.service)
            if not client.wait_for_service(timeout_sec=args.timeout):
                print(f"no service {args.service} within {args.timeout:g} s", file=sys.stderr)
                return 1
            future = client.call_async(LastMap.Request())
            rclpy.spin_until_future_complete(node, future, timeout_sec=max(0.1, deadline - time.monotonic()))
            reply = future.result()
            if reply is None or not reply.found:
                print("no answer" if reply is None else "no map made yet", file=sys.stderr)
                return 1
            print(json.dumps(as_dict(reply.stats)), flush=True)
            return 0
        # As the mapper offers it: reliable, transient local (a late subscriber gets the last one).
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(MapStats, args.topic, lambda m: (got.append(m), print(json.dumps(as_dict(m)), flush=True)), qos)
        while len(got) < args.n and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.2)
        if len(got) < args.n:
            print(f"{len(got)} of {args.n} on {args.topic} within {args.timeout:g} s", file=sys.stderr)
            return 1
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
