"""The API manager's ROS 2 side (rclpy), imported by api_manager.py on a clone whose ROS environment
names no master (docs/services.md, API manager). Runs on Debian's python3 with the distro's venv on
its path (ros-run: rclpy, cv2, numpy); nothing from ccrp.

The robot's images are subscribed best effort (which matches a reliable publisher as well as a
best-effort one), depth 1: only the newest frame matters. The result is a std_msgs/String,
reliable and volatile, as rclpy's default publisher.
"""

from __future__ import annotations

import os
import signal
import tempfile
import threading


def stamp_of(msg) -> float:
    """A ROS 2 header stamp (sec, nanosec) in seconds."""
    return msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9


class Ros2:
    """One node, spun by a thread of its own (the image callback); the service's worker thread
    publishes, which rclpy allows while it spins. A stop (SIGTERM, from systemd) ends the spinning
    thread before the node and rclpy are shut down: rclpy's own SIGTERM handling with a thread
    still inside the executor made the process abort at exit ("terminate called without an active
    exception", SIGABRT; seen in tests/e2e/test_jazzy_fleet.py)."""

    def __init__(self, cfg: dict, on_image) -> None:
        # The relay's Fast DDS profile (UDP only: shared memory does not cross users, and this
        # agent is its own user), the same discovery as ros.env's (this host and the robot).
        from relay_ros2 import fastdds_profile, write_atomic

        run = os.environ.get("RUNTIME_DIRECTORY") or tempfile.mkdtemp(prefix="ccrp-api-manager-")
        profile = os.path.join(run.split(":")[0], "fastdds.xml")
        write_atomic(profile, fastdds_profile(os.environ.pop("ROS_STATIC_PEERS", "")))
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = profile
        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "SYSTEM_DEFAULT"

        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import Image
        from std_msgs.msg import String

        self.rclpy, self.String = rclpy, String
        self.stop = threading.Event()
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        signal.signal(signal.SIGTERM, lambda *_: self.stop.set())
        signal.signal(signal.SIGINT, lambda *_: self.stop.set())
        self.node = rclpy.create_node("ccrp_api_manager")
        self.pub = self.node.create_publisher(String, cfg["output"], 10)
        newest = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
        self.node.create_subscription(Image, cfg["input"], on_image, newest)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.spinner = threading.Thread(target=self.spin, name="rclpy", daemon=True)
        self.spinner.start()

    def spin(self) -> None:
        while not self.stop.is_set():
            self.executor.spin_once(timeout_sec=0.1)

    def publish(self, text: str) -> None:
        self.pub.publish(self.String(data=text))

    stamp = staticmethod(stamp_of)

    def ok(self) -> bool:
        return not self.stop.is_set() and self.rclpy.ok()

    def close(self) -> None:
        self.stop.set()
        self.spinner.join()
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.try_shutdown()
