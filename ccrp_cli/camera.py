"""`ccrp robot camera` and the dashboard's camera view: the latest frame of a robot's camera topic as
its clone sees it, read on the clone by a short script run through the provider's exec (a ROS
node there, rospy or rclpy, waits for one sensor_msgs/Image and encodes it as JPEG with the
clone's OpenCV)."""

from __future__ import annotations

import base64
import json
import re
import time
from dataclasses import dataclass

from .errors import CcrpError, InputError, shown

DEFAULT_TOPIC = "/camera/image_raw"
TOPIC_RE = r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*"
MAX_JPEG = 4 * 1024 * 1024  # a frame bigger than this is not a camera view (and would not fit an exec answer)

# Run on the clone as `python3 -c READER TOPIC TIMEOUT`: names and numbers are arguments, never
# shell text. Its last line is one JSON object: the frame, or {"error", "why"}. One reader per ROS
# generation, the same head (OpenCV) and tail (checks, JPEG) around how each gets one message.
_HEAD = r'''
import base64, json, os, sys, time
topic, timeout = sys.argv[1], float(sys.argv[2])
def done(**d):
    sys.stdout.write("\n" + json.dumps(d) + "\n"); sys.stdout.flush(); os._exit(0)
try:
    import numpy as np, cv2
except ImportError as e:
    done(error="the clone has no OpenCV for python3 (%s): the clone image's pip packages (snapshots/<distro>.yaml)" % e, why="unavailable")
'''
_ROS1 = r'''import rosgraph, rospy
from sensor_msgs.msg import Image
# The master first: rospy.init_node would wait for an unreachable master for ever.
try:
    published = dict(rosgraph.Master("/ccrp_camera").getPublishedTopics(""))
except Exception as e:
    done(error="the clone's ROS master does not answer (%s)" % e, why="no-master")
name = topic if topic.startswith("/") else "/" + topic
if name not in published:
    done(error="nothing publishes %s on the clone's master (is the robot connected, with a camera?)" % name, why="no-publisher")
if published[name] != "sensor_msgs/Image":
    done(error="%s is a %s, not a sensor_msgs/Image" % (name, published[name]), why="bad-type")
rospy.init_node("ccrp_camera", anonymous=True, disable_signals=True, disable_rosout=True)
try:
    msg = rospy.wait_for_message(name, Image, timeout=timeout)
except Exception:
    done(error="no frame on %s within %g s" % (name, timeout), why="no-frame")
received = time.time()
seq, stamp = msg.header.seq, msg.header.stamp.to_sec()
'''
_ROS2 = r'''import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image
rclpy.init()
node = rclpy.create_node("ccrp_camera")
name = topic if topic.startswith("/") else "/" + topic
# The robot's publishers, found by discovery through the tunnel (ROS 2 has no master to ask).
end, kinds = time.time() + min(timeout, 3.0), []
while time.time() < end and not kinds:
    rclpy.spin_once(node, timeout_sec=0.1)
    kinds = dict(node.get_topic_names_and_types()).get(name, [])
if not kinds:
    done(error="nothing publishes %s on the clone's graph (is the robot connected, with a camera?)" % name, why="no-publisher")
if "sensor_msgs/msg/Image" not in kinds:
    done(error="%s is a %s, not a sensor_msgs/msg/Image" % (name, ",".join(kinds)), why="bad-type")
got = []
# Best effort takes a reliable publisher's frames as well as a best-effort one's.
node.create_subscription(Image, name, got.append, qos_profile_sensor_data)
end = time.time() + timeout
while time.time() < end and not got:
    rclpy.spin_once(node, timeout_sec=0.1)
if not got:
    done(error="no frame on %s within %g s" % (name, timeout), why="no-frame")
received, msg = time.time(), got[0]
seq, stamp = 0, msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9  # a ROS 2 header has no seq
'''
_ENCODE = r'''channels = {"rgb8": 3, "bgr8": 3, "mono8": 1, "rgba8": 4, "bgra8": 4}.get(msg.encoding)
if channels is None:
    done(error="frames in %s are not shown (rgb8, bgr8, mono8, rgba8, bgra8 are)" % msg.encoding, why="bad-frame")
h, w, step = msg.height, msg.width, msg.step
data = np.frombuffer(msg.data, dtype=np.uint8)
if h < 1 or w < 1 or step < w * channels or data.size < h * step:
    done(error="a malformed %dx%d %s frame (step %d, %d bytes)" % (w, h, msg.encoding, step, data.size), why="bad-frame")
img = data[:h * step].reshape(h, step)[:, :w * channels]
img = img.reshape(h, w) if channels == 1 else img.reshape(h, w, channels)
convert = {"rgb8": cv2.COLOR_RGB2BGR, "rgba8": cv2.COLOR_RGBA2BGR, "bgra8": cv2.COLOR_BGRA2BGR}.get(msg.encoding)
if convert is not None:
    img = cv2.cvtColor(img, convert)
ok, jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
if not ok:
    done(error="OpenCV could not encode the frame", why="bad-frame")
done(topic=name, width=w, height=h, encoding=msg.encoding, seq=seq, frame_id=msg.header.frame_id,
     stamp=stamp or None, age_ms=round((received - stamp) * 1000, 1) if stamp else None,
     jpeg=base64.b64encode(jpeg.tobytes()).decode())
'''
READER, READER2 = _HEAD + _ROS1 + _ENCODE, _HEAD + _ROS2 + _ENCODE

# The clone's ROS environment, then the reader (evaluation.IN_ROS's prelude; a constant). A ROS 2
# clone's setup.sh puts the wheels' venv (rclpy, OpenCV) on Debian's python3 path.
_PRELUDE = ['/bin/sh', '-c', 'set -a; . /etc/ccrp/ros.env; set +a; '
            'if [ -f "/opt/ros/$ROS_DISTRO/setup.sh" ]; then . "/opt/ros/$ROS_DISTRO/setup.sh"; fi; exec "$@"',
            'ccrp-camera', '/usr/bin/python3', '-c']
IN_ROS, IN_ROS2 = [*_PRELUDE, READER], [*_PRELUDE, READER2]


class NoFrame(CcrpError):
    """The clone answered, but with no frame: no robot, no camera, a silent camera, no OpenCV."""

    def __init__(self, message: str, why: str, hint: str | None = None) -> None:
        super().__init__(message, hint=hint)
        self.why = why


@dataclass
class Frame:
    robot: str
    topic: str
    jpeg: bytes
    width: int
    height: int
    encoding: str
    seq: int
    frame_id: str
    stamp: float | None  # the robot's header stamp, seconds since the epoch
    age_ms: float | None  # the frame's age when the clone received it (robot clock vs clone clock)
    read_ms: float  # the whole read: exec, node start, wait, encode

    def public(self) -> dict:
        """Everything but the picture (`--json`, the dashboard's headers)."""
        return {"robot": self.robot, "topic": self.topic, "width": self.width, "height": self.height,
                "encoding": self.encoding, "seq": self.seq, "frame_id": self.frame_id, "stamp": self.stamp,
                "age_ms": self.age_ms, "read_ms": self.read_ms, "bytes": len(self.jpeg)}


def check_topic(topic: str) -> None:
    if len(topic) > 200 or not re.fullmatch(TOPIC_RE, topic):
        raise InputError(f"--topic {shown(topic)} is not a ROS topic name", hint=f"e.g. --topic {DEFAULT_TOPIC}")


def latest_frame(fleet, provider, robot: str, topic: str = DEFAULT_TOPIC, timeout: float = 3.0) -> Frame:
    """One frame of `topic` as the robot's clone sees it. No fleet lock: it changes nothing ccrp
    records, and the dashboard polls it."""
    check_topic(topic)
    fleet.robot(fleet.store.load_state(), robot)  # a robot of this fleet, or exit 2
    if robot not in provider.query():
        raise NoFrame(f"robot {robot!r} has no clone", "no-clone", hint=f"ccrp clone create -i INVENTORY --robot {robot}")
    t0 = time.perf_counter()
    try:
        reader = IN_ROS2 if fleet.inventory.ros.ros2 else IN_ROS
        rc, out = provider.exec(robot, [*reader, topic, f"{timeout:g}"], timeout=timeout + 30)
    except CcrpError as exc:  # the clone is stopped or unreachable
        raise NoFrame(f"robot {robot!r}: its clone did not run the camera reader: {exc.message}", "no-clone",
                      hint="ccrp status -i INVENTORY") from None
    read_ms = round((time.perf_counter() - t0) * 1000, 1)
    last = next((ln for ln in reversed(out.strip().splitlines()) if ln.startswith("{")), "")
    try:
        got = json.loads(last)
    except ValueError:
        raise NoFrame(f"the camera reader failed on the clone of {robot!r} (exit {rc}): {' '.join(out.split())[-300:]}",
                      "failed", hint="is the clone serving? `ccrp status -i INVENTORY`") from None
    if "error" in got:
        raise NoFrame(f"robot {robot!r}: {got['error']}", str(got.get("why", "failed")),
                      hint="ccrp status -i INVENTORY (VPN, robot nodes)")
    try:
        jpeg = base64.b64decode(got["jpeg"], validate=True)
        frame = Frame(robot=robot, topic=str(got["topic"]), jpeg=jpeg, width=int(got["width"]), height=int(got["height"]),
                      encoding=str(got["encoding"]), seq=int(got["seq"]), frame_id=str(got.get("frame_id") or ""),
                      stamp=None if got.get("stamp") is None else float(got["stamp"]),
                      age_ms=None if got.get("age_ms") is None else float(got["age_ms"]), read_ms=read_ms)
    except (KeyError, TypeError, ValueError) as exc:
        raise NoFrame(f"the camera reader on the clone of {robot!r} answered something else: {shown(str(exc))}", "failed") from None
    if not (jpeg.startswith(b"\xff\xd8") and jpeg.rstrip(b"\0").endswith(b"\xff\xd9")) or len(jpeg) > MAX_JPEG:
        raise NoFrame(f"the camera reader on the clone of {robot!r} sent no JPEG ({len(jpeg)} bytes)", "failed")
    return frame
