#!/usr/bin/env python3
"""Waits for the first /map (nav_msgs/OccupancyGrid) from the robot's clone and prints one line
of JSON, {"width": W, "height": H, "occupied": N, "free": M}, then exits 0; exits 1 if none came
within --timeout seconds (default 60).

ROS 1 (rospy) or ROS 2 (rclpy), whichever imports: rclpy first when ROS_VERSION=2, else rospy
first. Run it as fake_scan.py: python3 (ROS 1) or /opt/ros/jazzy/bin/python (ROS 2).
"""
import argparse
import json
import os
import sys
import threading
import time


def ros_flavour():
    """1 or 2: the ROS this python can import."""
    order = [2, 1] if os.environ.get("ROS_VERSION") == "2" else [1, 2]
    for v in order:
        try:
            __import__("rclpy" if v == 2 else "rospy")
            return v
        except ImportError:
            pass
    sys.exit("wait_map: neither rospy nor rclpy imports with this python")


def summary(m):
    data = list(m.data)
    return {"width": m.info.width, "height": m.info.height,
            "occupied": sum(1 for v in data if v > 50), "free": sum(1 for v in data if v == 0)}


def wait_ros1(timeout):
    import rospy
    from nav_msgs.msg import OccupancyGrid

    rospy.init_node("wait_map", anonymous=True, disable_signals=True)
    try:  # the node's /map is latched: a map published before we came is delivered too
        return rospy.wait_for_message("/map", OccupancyGrid, timeout=timeout)
    except rospy.ROSException:
        return None


def wait_ros2(timeout):
    import rclpy
    from nav_msgs.msg import OccupancyGrid
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    rclpy.init()
    node = rclpy.create_node("wait_map")
    got = []
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)  # the last map, if published before
    node.create_subscription(OccupancyGrid, "/map", got.append, qos)
    deadline = time.monotonic() + timeout
    while not got and time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=min(0.5, max(0.0, deadline - time.monotonic())))
    node.destroy_node()
    rclpy.try_shutdown()
    return got[0] if got else None


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--timeout", type=float, default=60.0, help="seconds to wait (default 60)")
    args = p.parse_args()
    # Also when ROS itself hangs (rospy's init_node waits for the master however long it takes).
    watchdog = threading.Timer(args.timeout + 5, give_up, (args.timeout,))
    watchdog.daemon = True
    watchdog.start()
    m = (wait_ros2 if ros_flavour() == 2 else wait_ros1)(args.timeout)
    if m is None:
        give_up(args.timeout)
    print(json.dumps(summary(m)), flush=True)
    os._exit(0)  # at once, whatever threads ROS left behind


def give_up(timeout):
    print(f"wait_map: no /map within {timeout:g} s", file=sys.stderr, flush=True)
    os._exit(1)


if __name__ == "__main__":
    main()
