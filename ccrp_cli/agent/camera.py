"""ccrp camera agent, on a clone: keeps the newest frame of each camera topic it was asked for, and
answers `ccrp robot camera` and the dashboard's camera view on a Unix socket with it as a JPEG.

Started on the first read (camera.py pushes this file and runs it as a transient unit, as the `ros`
user, in the robot's ROS environment), it subscribes to a topic when the topic is first asked for
and ends after IDLE seconds without a request: a view open in a page costs one subscriber, and a
read costs the socket round trip and one JPEG encode, not a node's start (rospy or rclpy, OpenCV).
A frame older than STALE_S when asked for is waited for anew (the robot went away: no stale
picture is served as the latest).

`python3 camera.py SOCKET IDLE`; a request is one JSON line {"topic", "timeout"}, the answer one
JSON line: the frame ({"topic", "width", "height", "encoding", "seq", "frame_id", "stamp",
"age_ms", "jpeg": base64}) or {"error", "why"}.
"""
import base64
import json
import os
import socket
import sys
import threading
import time

STALE_S = 3.0
CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}


class NoFrame(Exception):
    def __init__(self, error, why):
        super().__init__(error)
        self.answer = {"error": error, "why": why}


def encode(msg, received, seq, stamp):
    """A sensor_msgs Image -> the answer with its JPEG (the clone's OpenCV)."""
    import cv2
    import numpy as np

    channels = CHANNELS.get(msg.encoding)
    if channels is None:
        raise NoFrame(f"frames in {msg.encoding} are not shown ({', '.join(CHANNELS)} are)", "bad-frame")
    h, w, step = msg.height, msg.width, msg.step
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if h < 1 or w < 1 or step < w * channels or data.size < h * step:
        raise NoFrame(f"a malformed {w}x{h} {msg.encoding} frame (step {step}, {data.size} bytes)", "bad-frame")
    img = data[:h * step].reshape(h, step)[:, :w * channels]
    img = img.reshape(h, w) if channels == 1 else img.reshape(h, w, channels)
    convert = {"rgb8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGBA2BGR, "bgra8": cv2.COLOR_BGRA2BGR}.get(msg.encoding)
    if convert is not None:
        img = cv2.cvtColor(img, convert)
    ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    if not ok:
        raise NoFrame("OpenCV could not encode the frame", "bad-frame")
    return {"width": w, "height": h, "encoding": msg.encoding, "seq": seq, "frame_id": msg.header.frame_id,
            "stamp": stamp or None, "age_ms": round((received - stamp) * 1000, 1) if stamp else None,
            "jpeg": base64.b64encode(jpeg.tobytes()).decode()}


class Ros1:
    """rospy: the master says who publishes what. The node starts with the first subscription,
    once the master answered: rospy.init_node would wait for an unreachable master for ever."""

    def __init__(self):
        self.rospy = None

    def subscribe(self, name, keep):
        import rosgraph
        from sensor_msgs.msg import Image

        try:
            published = dict(rosgraph.Master("/ccrp_camera").getPublishedTopics(""))
        except Exception as exc:  # noqa: BLE001 - any master failure is one answer
            raise NoFrame(f"the clone's ROS master does not answer ({exc})", "no-master") from None
        if name not in published:
            raise NoFrame(f"nothing publishes {name} on the clone's master (is the robot connected, with a camera?)",
                          "no-publisher")
        if published[name] != "sensor_msgs/Image":
            raise NoFrame(f"{name} is a {published[name]}, not a sensor_msgs/Image", "bad-type")
        if self.rospy is None:
            import rospy

            rospy.init_node("ccrp_camera", anonymous=True, disable_signals=True, disable_rosout=True)
            self.rospy = rospy
        self.rospy.Subscriber(name, Image, lambda m: keep(m, m.header.seq, m.header.stamp.to_sec()), queue_size=1,
                              buff_size=2 ** 24, tcp_nodelay=True)

    def close(self):
        if self.rospy is not None:
            self.rospy.signal_shutdown("idle")


class Ros2:
    """rclpy: the graph, found by discovery through the tunnel (ROS 2 has no master), spun in a
    thread of its own that close() ends before the process does (rclpy aborts otherwise)."""

    def __init__(self):
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        # No rclpy signal handlers: SIGTERM (systemctl stop) ends the agent at once, as the relay's
        # (relay_ros2.py); rclpy's would shut its context under the spinner thread.
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        self.rclpy, self.node, self.stop = rclpy, rclpy.create_node("ccrp_camera"), threading.Event()
        self.lock = threading.Lock()  # the node is not thread-safe: spin and subscribe take turns
        self.spinner = threading.Thread(target=self.spin, daemon=True)
        self.spinner.start()

    def spin(self):
        while not self.stop.is_set():
            with self.lock:
                self.rclpy.spin_once(self.node, timeout_sec=0.05)
            time.sleep(0.001)

    def subscribe(self, name, keep):
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Image

        end, kinds = time.time() + 3.0, []
        while time.time() < end and not kinds:
            with self.lock:
                kinds = dict(self.node.get_topic_names_and_types()).get(name, [])
            time.sleep(0.1)
        if not kinds:
            raise NoFrame(f"nothing publishes {name} on the clone's graph (is the robot connected, with a camera?)",
                          "no-publisher")
        if "sensor_msgs/msg/Image" not in kinds:
            raise NoFrame(f"{name} is a {','.join(kinds)}, not a sensor_msgs/msg/Image", "bad-type")
        stamp = lambda m: m.header.stamp.sec + m.header.stamp.nanosec / 1e9  # noqa: E731
        with self.lock:  # best effort takes a reliable publisher's frames as well as a best-effort one's
            self.node.create_subscription(Image, name, lambda m: keep(m, 0, stamp(m)), qos_profile_sensor_data)

    def close(self):
        self.stop.set()
        self.spinner.join()
        self.node.destroy_node()
        self.rclpy.shutdown()


class Frames:
    """The newest frame of each topic asked for (`ros` subscribes), and what a request gets."""

    def __init__(self, ros):
        self.ros, self.latest, self.cond = ros, {}, threading.Condition()

    def keeper(self, name):
        def keep(msg, seq, stamp):
            with self.cond:
                self.latest[name] = (msg, time.time(), seq, stamp)
                self.cond.notify_all()
        return keep

    def answer(self, topic, timeout):
        name = topic if topic.startswith("/") else "/" + topic
        try:
            with self.cond:
                known = name in self.latest
            if not known:
                self.ros.subscribe(name, self.keeper(name))
                with self.cond:
                    self.latest.setdefault(name, None)
            with self.cond:
                fresh = self.cond.wait_for(lambda: self.latest[name] and time.time() - self.latest[name][1] < STALE_S,
                                           timeout=timeout)
                if not fresh:
                    raise NoFrame(f"no frame on {name} within {timeout:g} s", "no-frame")
                msg, received, seq, stamp = self.latest[name]
            return {"topic": name, **encode(msg, received, seq, stamp)}
        except NoFrame as exc:
            return exc.answer


def serve(server, frames, idle):
    """One request at a time (the dashboard sends one per robot); ends after `idle` s of none."""
    server.settimeout(1.0)
    last = time.monotonic()
    while time.monotonic() - last < idle:
        try:
            conn, _ = server.accept()
        except socket.timeout:
            continue
        with conn:
            conn.settimeout(70)
            try:
                req = json.loads(conn.makefile("rb").readline(4096) or b"{}")
                topic, timeout = str(req["topic"]), min(max(float(req.get("timeout", 3)), 0.1), 60)
                conn.sendall((json.dumps(frames.answer(topic, timeout)) + "\n").encode())
            except (OSError, ValueError, KeyError, TypeError) as exc:
                print(f"ccrp-camera: a request failed: {exc}", file=sys.stderr, flush=True)
        last = time.monotonic()


def main():
    path, idle = sys.argv[1], float(sys.argv[2])
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o077)
    server.bind(path)  # 0600: root (ccrp's exec) and this user only
    os.umask(old)
    server.listen(4)
    ros = Ros1() if os.environ.get("ROS_MASTER_URI") else Ros2()
    print(f"ccrp-camera: serving frames on {path}", flush=True)
    try:
        serve(server, Frames(ros), idle)
    finally:
        server.close()
        os.unlink(path)
        ros.close()


if __name__ == "__main__":
    main()
