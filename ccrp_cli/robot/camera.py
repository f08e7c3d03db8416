"""`ccrp robot camera` and the dashboard's camera view: the latest frame of a robot's camera topic as
its clone sees it. A camera agent on the clone (agent/camera.py, ending after CAMERA_IDLE_S without
a read) keeps the newest frame of each topic asked for; a read is one exec of a small client that
asks it on its Unix socket and prints its answer (a JPEG made with the clone's OpenCV).

Who starts the agent: `ccrp robot camera` (its first read), and the dashboard's Camera button
(start_camera, a POST under the page's CSRF and Origin checks). The dashboard's frame reads, GETs,
start nothing (latest_frame with start=False): without an agent they answer NoFrame "no-agent".
The agent's file, unit and socket are the camera service's (services/camera.py), whose file
`fleet up` keeps on every clone."""

from __future__ import annotations

import base64
import json
import re
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import CcrpError, InputError, shown
from ..services.camera import AGENT, CAMERA_IDLE_S, SOCKET, UNIT, UNIT_OPTIONS, agent_file

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Lifecycle, Reaches

DEFAULT_TOPIC = "/camera/image_raw"
TOPIC_RE = r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*"
MAX_JPEG = 4 * 1024 * 1024  # a frame bigger than this is not a camera view (and would not fit an exec answer)

# Run on the clone as `python3 -c ASK SOCKET TOPIC TIMEOUT` (names and numbers are arguments, never
# shell text; standard library only, so it starts in milliseconds). Prints the agent's answer, or
# {"why": "no-agent"} when none serves.
ASK = r"""
import json, socket, sys
path, topic, timeout = sys.argv[1], sys.argv[2], float(sys.argv[3])
try:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout + 15)
    s.connect(path)
except OSError as e:
    print(json.dumps({"error": "no camera agent serves (%s)" % e, "why": "no-agent"})); sys.exit(0)
s.sendall((json.dumps({"topic": topic, "timeout": timeout}) + "\n").encode())
print(s.makefile("rb").readline().decode() or json.dumps({"error": "the camera agent ended the request", "why": "no-agent"}))
"""
ASK_ARGV = ["python3", "-c", ASK, SOCKET]


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


def _check_robot(fleet: Fleet, provider: Lifecycle, robot: str) -> None:
    fleet.robot(fleet.store.load_state(), robot)  # a robot of this fleet, or exit 2
    if robot not in provider.query():
        raise NoFrame(f"robot {robot!r} has no clone", "no-clone", hint=f"ccrp clone create -i INVENTORY --robot {robot}")


def latest_frame(fleet: Fleet, provider: Lifecycle, robot: str, topic: str = DEFAULT_TOPIC, timeout: float = 3.0,
                 start: bool = True) -> Frame:
    """One frame of `topic` as the robot's clone sees it. No fleet lock: it changes nothing ccrp
    records, and the dashboard polls it. Without `start` (the dashboard's GET) a clone whose agent
    does not run is NoFrame "no-agent", and nothing is started there."""
    check_topic(topic)
    _check_robot(fleet, provider, robot)
    t0 = time.perf_counter()
    try:
        got = _ask(provider, robot, topic, timeout)
        if got.get("why") == "no-agent":  # the first read since the clone booted, or after an idle spell
            if not start:
                raise NoFrame(f"no camera agent runs on the clone of {robot!r} (not started, or ended after "
                              f"{CAMERA_IDLE_S} s without a read)", "no-agent",
                              hint=f"start it: the dashboard's Camera button, or `ccrp robot camera --robot {robot}`")
            start_agent(provider, robot)
            got = _ask_until_served(provider, robot, topic, timeout)
    except NoFrame:
        raise
    except CcrpError as exc:  # the clone is stopped or unreachable
        raise NoFrame(f"robot {robot!r}: its clone did not answer the camera read: {exc.message}", "no-clone",
                      hint="ccrp status -i INVENTORY") from None
    read_ms = round((time.perf_counter() - t0) * 1000, 1)
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
        raise NoFrame(f"the camera agent on the clone of {robot!r} answered something else: {shown(str(exc))}", "failed") from None
    if not (jpeg.startswith(b"\xff\xd8") and jpeg.rstrip(b"\0").endswith(b"\xff\xd9")) or len(jpeg) > MAX_JPEG:
        raise NoFrame(f"the camera agent on the clone of {robot!r} sent no JPEG ({len(jpeg)} bytes)", "failed")
    return frame


def start_camera(fleet: Fleet, provider: Lifecycle, robot: str, topic: str = DEFAULT_TOPIC, timeout: float = 3.0) -> dict:
    """The dashboard's Camera button (a POST): the camera agent on the robot's clone, started unless
    one serves, and asked until it does. {"robot", "agent": "running" | "started"}."""
    check_topic(topic)
    _check_robot(fleet, provider, robot)
    try:
        if _ask(provider, robot, topic, timeout).get("why") != "no-agent":
            return {"robot": robot, "agent": "running"}
        start_agent(provider, robot)
        _ask_until_served(provider, robot, topic, timeout)
    except NoFrame:
        raise
    except CcrpError as exc:  # the clone is stopped or unreachable
        raise NoFrame(f"robot {robot!r}: its clone did not answer: {exc.message}", "no-clone",
                      hint="ccrp status -i INVENTORY") from None
    return {"robot": robot, "agent": "started"}


def _ask(provider: Reaches, robot: str, topic: str, timeout: float) -> dict:
    """The agent's answer through the client (one exec), as a dict."""
    rc, out = provider.transport.exec(robot, [*ASK_ARGV, topic, f"{timeout:g}"], timeout=timeout + 30)
    last = next((ln for ln in reversed(out.strip().splitlines()) if ln.startswith("{")), "")
    try:
        got = json.loads(last)
    except ValueError:
        got = None
    if not isinstance(got, dict):
        raise NoFrame(f"the camera read failed on the clone of {robot!r} (exit {rc}): {' '.join(out.split())[-300:]}",
                      "failed", hint="is the clone serving? `ccrp status -i INVENTORY`")
    return got


def start_agent(provider: Reaches, robot: str) -> None:
    """The camera agent on the clone, (re)started from this ccrp's copy of it: `fleet up` puts that
    copy there (services/camera.py); a clone without it (made before, or not brought up since ccrp
    changed) gets it pushed here first."""
    from ..probe import files_current
    from .evaluation import ROS_PRELUDE
    from .simulated import run_unit

    agent = agent_file()
    if not files_current(provider, robot, [agent]):
        provider.transport.push_files(robot, [agent], restart=[])
    argv = [*ROS_PRELUDE, "ccrp-camera", "/usr/bin/python3", AGENT, SOCKET, str(CAMERA_IDLE_S)]
    run_unit(lambda cmd: provider.transport.exec(robot, cmd, timeout=30), UNIT, argv, f"the clone of {robot!r}", UNIT_OPTIONS)


def _ask_until_served(provider: Reaches, robot: str, topic: str, timeout: float) -> dict:
    """Asks until the agent just started serves (its node and OpenCV load in a second or two)."""
    from ..retry import PollTimeout, poll

    try:
        return poll(lambda: ((got := _ask(provider, robot, topic, timeout)).get("why") != "no-agent", got),
                    timeout=30, interval=0.3)
    except PollTimeout:
        _, log = provider.transport.exec(robot, ["journalctl", "-u", UNIT, "-n", "5", "--no-pager"], timeout=15)
        raise NoFrame(f"the camera agent did not start on the clone of {robot!r}: {' '.join(log.split())[-300:]}",
                      "failed") from None
