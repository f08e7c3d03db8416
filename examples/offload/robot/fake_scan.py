#!/usr/bin/env python3
"""The robot's half of the offloading example: a synthetic laser scan on /scan
(sensor_msgs/LaserScan) at 5 Hz, the robot in the middle of a room of 2 m x 3 m, 180 beams all
around. Its clone's scan_to_map node answers with /map.

ROS 1 (rospy) or ROS 2 (rclpy), whichever imports: rclpy first when ROS_VERSION=2, else rospy
first. Run it with the robot's ROS python: python3 (ROS 1) or /opt/ros/jazzy/bin/python (ROS 2),
in the robot's ROS environment (/etc/ccrp/ros.env, e.g. through a login shell: bash -l).
"""
import argparse
import math
import os
import sys

BEAMS = 180
ROOM = (2.0, 3.0)  # metres along x and y, the robot at its centre
RANGE_MIN, RANGE_MAX = 0.05, 10.0
ANGLE_MIN = -math.pi
ANGLE_INCREMENT = 2 * math.pi / BEAMS


def room_ranges(beams=BEAMS, room=ROOM):
    """Each beam's distance to the room's walls."""
    hx, hy = room[0] / 2.0, room[1] / 2.0
    out = []
    for k in range(beams):
        a = ANGLE_MIN + k * ANGLE_INCREMENT
        c, s = abs(math.cos(a)), abs(math.sin(a))
        out.append(min(hx / c if c > 1e-9 else math.inf, hy / s if s > 1e-9 else math.inf))
    return out


def ros_flavour():
    """1 or 2: the ROS this python can import."""
    order = [2, 1] if os.environ.get("ROS_VERSION") == "2" else [1, 2]
    for v in order:
        try:
            __import__("rclpy" if v == 2 else "rospy")
            return v
        except ImportError:
            pass
    sys.exit("fake_scan: neither rospy nor rclpy imports with this python")


def fill(scan, ranges):
    scan.header.frame_id = "laser"
    scan.angle_min = ANGLE_MIN
    scan.angle_max = ANGLE_MIN + (BEAMS - 1) * ANGLE_INCREMENT
    scan.angle_increment = ANGLE_INCREMENT
    scan.range_min, scan.range_max = RANGE_MIN, RANGE_MAX
    scan.ranges = ranges
    return scan


def run_ros1(rate, ranges):
    import rospy
    from sensor_msgs.msg import LaserScan

    rospy.init_node("fake_scan")
    pub = rospy.Publisher("/scan", LaserScan, queue_size=10)
    tick = rospy.Rate(rate)
    print(f"fake_scan: ROS 1, /scan at {rate} Hz", flush=True)
    while not rospy.is_shutdown():
        scan = fill(LaserScan(), ranges)
        scan.header.stamp = rospy.Time.now()
        pub.publish(scan)
        try:
            tick.sleep()
        except rospy.ROSInterruptException:
            break


def run_ros2(rate, ranges):
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from sensor_msgs.msg import LaserScan

    rclpy.init()
    node = rclpy.create_node("fake_scan")
    pub = node.create_publisher(LaserScan, "/scan", 10)

    def tick():
        scan = fill(LaserScan(), ranges)
        scan.header.stamp = node.get_clock().now().to_msg()
        pub.publish(scan)

    node.create_timer(1.0 / rate, tick)
    print(f"fake_scan: ROS 2, /scan at {rate} Hz", flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rate", type=float, default=5.0, help="scans a second (default 5)")
    args = p.parse_args()
    ranges = room_ranges()
    try:
        (run_ros2 if ros_flavour() == 2 else run_ros1)(args.rate, ranges)
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
