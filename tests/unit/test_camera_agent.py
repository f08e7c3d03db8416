"""The camera agent (agent/camera.py) with a stand-in for ROS: the newest frame kept per topic, a
stale one waited for anew, errors answered, the JPEG made by OpenCV; the client `ccrp robot camera`
runs on the clone, over a real Unix socket; and the read's flow on a fake clone (the agent started
on the first read)."""

from __future__ import annotations

import base64
import json
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

import pytest

cv2 = pytest.importorskip("cv2", reason="needs OpenCV (the clone's; opencv-contrib-python-headless here)")
np = pytest.importorskip("numpy")

from ccrp_cli.robot import camera  # noqa: E402
from ccrp_cli.agent import camera as agent  # noqa: E402


def image(w=32, h=16, encoding="rgb8", rgb=(200, 40, 90), frame_id="nao1_camera", stamp=1700000000.5):
    data = bytes(rgb) * (w * h) if encoding == "rgb8" else bytes(w * h)
    step = w * (3 if encoding == "rgb8" else 1)
    header = SimpleNamespace(frame_id=frame_id, stamp=SimpleNamespace(sec=int(stamp)))
    return SimpleNamespace(width=w, height=h, step=step, encoding=encoding, data=data, header=header)


class FakeRos:
    """Knows one camera topic; a subscription hands back the keeper, as rospy/rclpy call it."""

    def __init__(self):
        self.keepers = {}

    def subscribe(self, name, keep):
        if name == "/chatter":
            raise agent.NoFrame(f"{name} is a std_msgs/String, not a sensor_msgs/Image", "bad-type")
        if name != "/camera/image_raw":
            raise agent.NoFrame(f"nothing publishes {name} on the clone's master", "no-publisher")
        self.keepers[name] = keep


def publish_soon(ros, msg, delay=0.2, seq=7, stamp=1700000000.5):
    def later():
        deadline = time.monotonic() + 5
        while "/camera/image_raw" not in ros.keepers and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(delay)
        ros.keepers["/camera/image_raw"](msg, seq, stamp)
    threading.Thread(target=later, daemon=True).start()


def test_the_newest_frame_is_answered_as_a_jpeg_and_a_stale_one_is_waited_for():
    ros = FakeRos()
    frames = agent.Frames(ros)
    publish_soon(ros, image())
    got = frames.answer("camera/image_raw", 5)  # subscribes, then waits for the first frame
    assert (got["topic"], got["width"], got["height"], got["encoding"], got["seq"]) == ("/camera/image_raw", 32, 16, "rgb8", 7)
    picture = cv2.imdecode(np.frombuffer(base64.b64decode(got["jpeg"]), np.uint8), cv2.IMREAD_COLOR)
    b, g, r = (int(v) for v in picture[8, 16])  # OpenCV is BGR: the rgb8 frame's red stays red
    assert abs(r - 200) < 20 and abs(g - 40) < 20 and abs(b - 90) < 20, (r, g, b)
    t0 = time.monotonic()
    assert frames.answer("/camera/image_raw", 5)["seq"] == 7 and time.monotonic() - t0 < 1  # kept: no wait
    # The robot went away: its last frame grows old, and is not served as the latest.
    name = "/camera/image_raw"
    msg, _, seq, stamp = frames.latest[name]
    frames.latest[name] = (msg, time.time() - agent.STALE_S - 1, seq, stamp)
    assert frames.answer(name, 0.3) == {"error": "no frame on /camera/image_raw within 0.3 s", "why": "no-frame"}
    publish_soon(ros, image(), seq=8)
    assert frames.answer(name, 5)["seq"] == 8


def test_errors_are_answers_and_bad_frames_are_refused():
    ros = FakeRos()
    frames = agent.Frames(ros)
    assert frames.answer("/chatter", 1)["why"] == "bad-type"
    assert frames.answer("/nothing", 1)["why"] == "no-publisher"
    publish_soon(ros, image(encoding="yuv422"))
    assert frames.answer("/camera/image_raw", 5)["why"] == "bad-frame"
    short = image()
    short.data = short.data[:100]
    with pytest.raises(agent.NoFrame, match="malformed"):
        agent.encode(short, time.time(), 0, 0)


def test_the_client_asks_the_agent_on_its_socket(tmp_path):
    """ASK, as it runs on the clone (a python3 -c with the socket, topic and timeout as arguments),
    against the agent's serve loop on a real Unix socket; without an agent it says so."""
    import socket

    sock = str(tmp_path / "camera.sock")
    ask = lambda: json.loads(subprocess.run([sys.executable, "-c", camera.ASK, sock, "/camera/image_raw", "3"],  # noqa: E731
                                            capture_output=True, text=True, timeout=30).stdout)
    assert ask()["why"] == "no-agent"
    ros = FakeRos()
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(sock)
    server.listen(4)
    done = threading.Event()
    thread = threading.Thread(target=lambda: (agent.serve(server, agent.Frames(ros), idle=2), done.set()), daemon=True)
    thread.start()
    publish_soon(ros, image())
    got = ask()
    assert got["width"] == 32 and base64.b64decode(got["jpeg"]).startswith(b"\xff\xd8")
    assert done.wait(10)  # idle: the agent ends by itself
    server.close()


class Clone:
    """A clone whose camera agent is not running until started (its unit's systemd-run)."""

    def __init__(self, frame: dict, held: dict[str, str] | None = None):
        self.frame, self.serving, self.ran, self.pushed = frame, False, [], []
        self.held = dict(held or {})  # path -> content of what the clone holds

    def query(self):
        return {"nao1": object()}

    transport = property(lambda self: self)  # a fake clone is its own transport
    def push_files(self, robot, files, restart=()):
        self.pushed += [f.dest for f in files]
        self.held.update({f.dest: f.content for f in files})

    def exec(self, robot, argv, timeout=60):
        import hashlib

        self.ran.append(argv)
        if argv[0] == "sha256sum":
            return 0, "".join(f"{hashlib.sha256(self.held[p].encode()).hexdigest()}  {p}\n" for p in argv[1:] if p in self.held)
        if argv[0] == "systemd-run":
            self.serving = True
        if argv[:len(camera.ASK_ARGV)] == camera.ASK_ARGV:
            return 0, json.dumps(self.frame if self.serving else {"error": "no camera agent serves", "why": "no-agent"})
        return 0, ""


def test_the_first_read_starts_the_agent_and_the_next_ones_only_ask(lab_up):
    fleet, _ = lab_up
    jpeg = cv2.imencode(".jpg", np.zeros((8, 16, 3), np.uint8))[1].tobytes()
    clone = Clone({"topic": "/camera/image_raw", "width": 16, "height": 8, "encoding": "rgb8", "seq": 3,
                   "frame_id": "nao1_camera", "stamp": None, "age_ms": None, "jpeg": base64.b64encode(jpeg).decode()})
    frame = camera.latest_frame(fleet, clone, "nao1")
    assert frame.jpeg == jpeg and clone.pushed == [camera.AGENT]
    run = next(argv for argv in clone.ran if argv[0] == "systemd-run")
    assert run[run.index("--unit") + 1] == camera.UNIT and "User=ros" in run and run[-3:] == [camera.AGENT, camera.SOCKET, "120"]
    assert not any("nao1" in a for argv in clone.ran for a in argv)  # names only ever as arguments of constants
    clone.ran.clear()
    assert camera.latest_frame(fleet, clone, "nao1").seq == 3
    assert len(clone.ran) == 1  # one exec: the client's question




def test_a_clone_holding_the_agent_gets_it_started_not_pushed(lab_up):
    """fleet up keeps the agent on every clone (services/camera.py): the first read only starts it.
    A clone without this copy (made before the service, or holding an older one) gets it pushed."""
    from ccrp_cli.services.camera import agent_file

    fleet, _ = lab_up
    jpeg = cv2.imencode(".jpg", np.zeros((8, 16, 3), np.uint8))[1].tobytes()
    frame = {"topic": "/camera/image_raw", "width": 16, "height": 8, "encoding": "rgb8", "seq": 3,
             "frame_id": "", "stamp": None, "age_ms": None, "jpeg": base64.b64encode(jpeg).decode()}
    clone = Clone(frame, held={camera.AGENT: agent_file().content})
    assert camera.latest_frame(fleet, clone, "nao1").seq == 3
    assert clone.pushed == [] and any(argv[0] == "systemd-run" for argv in clone.ran)
    older = Clone(frame, held={camera.AGENT: "# an older camera agent\n"})
    assert camera.start_camera(fleet, older, "nao1") == {"robot": "nao1", "agent": "started"}
    assert older.pushed == [camera.AGENT] and older.held[camera.AGENT] == agent_file().content
