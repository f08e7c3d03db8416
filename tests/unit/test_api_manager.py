"""The API manager (issue 14): its inventory setting, what `fleet up` pushes for it, and the
clone-side agent's filtering, error classes, retries and backends (google-vision against a local
endpoint speaking the Vision REST API; opencv on a photograph matplotlib ships)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from ccrp_cli.services import api_manager as service
from ccrp_cli.agent import api_manager as agent
from ccrp_cli.errors import CcrpError
from ccrp_cli.loader import parse_inventory
from tests.fakes.vision import FakeVision

BASE = {"fleet": "f", "provider": {"kind": "docker"}, "robots": [{"name": "nao1"}, {"name": "nao2"}]}


def inv(**extra):
    return parse_inventory({**BASE, **extra}, "ccrp.yaml")


# -- the inventory ------------------------------------------------------------------------------

def test_defaults_and_a_robot_replaces_the_fleets_setting():
    fleet = inv(services={"api_manager": {}},
                robots=[{"name": "nao1"},
                        {"name": "nao2", "services": {"api_manager": {"backend": "google-vision", "rate": 0.5,
                                                                      "min_confidence": 0.8}}},
                        {"name": "nao3", "services": {"api_manager": {"enabled": False}}}])
    s1, s2, s3 = (fleet.api_manager_of(r) for r in fleet.robots)
    assert (s1.input, s1.output, s1.backend, s1.rate, s1.min_confidence) == \
        ("/camera/image_raw", "/api_manager/result", "opencv", 1.0, 0.5)
    # The robot's own replaces the fleet's entirely (its input is the default again, not merged).
    assert (s2.backend, s2.rate, s2.min_confidence, s2.input) == ("google-vision", 0.5, 0.8, "/camera/image_raw")
    assert s3 is None
    assert inv().api_manager_of(inv().robots[0]) is None  # off unless asked for


@pytest.mark.parametrize("setting, why", [
    ({"rate": 0}, "services.api_manager.rate"),
    ({"rate": "fast"}, "'fast' is not a number"),
    ({"rate": True}, "True is not a number"),
    ({"rate": 31}, "services.api_manager.rate"),
    ({"min_confidence": 1.5}, "services.api_manager.min_confidence"),
    ({"input": "camera"}, "services.api_manager.input"),
    ({"input": "/a", "output": "/a"}, "input and output are the same topic /a"),
    ({"backend": "Google Vision"}, "services.api_manager.backend"),
    ({"colour": "blue"}, "services.api_manager.colour"),
    ({"google_vision": {"endpoint": "http://x y"}}, "services.api_manager.google_vision.endpoint"),
    ({"google_vision": {"timeout": 0}}, "services.api_manager.google_vision.timeout"),
    ({"options": {"a": [1]}}, "services.api_manager.options.a"),
])
def test_a_bad_setting_is_one_line_naming_the_key(setting, why):
    with pytest.raises(CcrpError) as err:
        inv(services={"api_manager": setting})
    line = err.value.one_line()
    assert why in line and "\n" not in line


def test_a_robots_bad_setting_names_the_robot():
    with pytest.raises(CcrpError) as err:
        inv(robots=[{"name": "nao1", "services": {"api_manager": {"rate": -1}}}])
    assert "robots[0].services.api_manager.rate" in err.value.one_line()


def test_pushed_config_and_key_never_in_user_data(tmp_path):
    key = tmp_path / "key.json"
    key.write_text(json.dumps({"type": "service_account", "private_key": "-----BEGIN PRIVATE KEY-----\n..."}))
    fleet = inv(services={"api_manager": {"backend": "google-vision", "options": {"features": "faces"},
                                          "google_vision": {"credentials": str(key), "endpoint": "http://10.0.0.1:8080"}}})
    files = service.api_manager_files(fleet, fleet.robots[0])
    assert [(f.dest, f.mode, f.group) for f in files] == [
        (service.API_CONFIG, 0o644, "root"), ("/usr/local/lib/ccrp/api_manager.py", 0o644, "root"),
        (service.GOOGLE_KEY, 0o640, "ccrp-api")]
    cfg = json.loads(files[0].content)
    assert cfg["google_vision"] == {"endpoint": "http://10.0.0.1:8080", "timeout": 5.0, "credentials": service.GOOGLE_KEY}
    assert cfg["robot"] == "nao1" and cfg["options"] == {"features": "faces"} and "PRIVATE" not in files[0].content
    assert files[2].content == key.read_text()
    # opencv needs no key (the config and the agent); no API manager, nothing pushed
    assert len(service.api_manager_files(inv(services={"api_manager": {}}), fleet.robots[0])) == 2
    assert service.api_manager_files(inv(), fleet.robots[0]) == []


def test_a_key_that_is_not_a_service_account_key_is_one_line(tmp_path):
    bad = tmp_path / "key.json"
    for text, why in (("{", "JSONDecodeError"), ('{"type": "authorized_user"}', "not a service-account key")):
        bad.write_text(text)
        fleet = inv(services={"api_manager": {"backend": "google-vision", "google_vision": {"credentials": str(bad)}}})
        with pytest.raises(CcrpError) as err:
            service.api_manager_files(fleet, fleet.robots[0])
        assert why in err.value.one_line()
        # The same refusal comes from the service's check, which ensure_clone runs before a clone exists.
        with pytest.raises(CcrpError) as err:
            service.ApiManager().check(SimpleNamespace(inventory=fleet), fleet.robots[0])
        assert why in err.value.one_line()
    good = {"api_manager": {"backend": "opencv"}}
    service.ApiManager().check(SimpleNamespace(inventory=inv(services=good)), inv(services=good).robots[0])


class Recorder:
    def __init__(self, rc=0):
        self.pushed, self.execs, self.rc = [], [], rc

    transport = property(lambda self: self)  # a fake clone is its own transport
    def push_files(self, robot, files, restart):
        self.pushed.append(([f.dest for f in files], restart))

    def exec(self, robot, argv, timeout=60):
        self.execs.append(argv)
        return self.rc, ""


def test_fleet_up_pushes_a_changed_config_restarting_the_agent_and_turns_it_off():
    from ccrp_cli.ops.clones import same  # noqa: F401 - apply_api_manager compares digests with it
    import hashlib

    fleet = inv(services={"api_manager": {}})
    files = service.api_manager_files(fleet, fleet.robots[0])
    p = Recorder()
    service.apply_api_manager(p, "nao1", files, {})
    # The agent goes with its config (a bare clone's user-data does not carry it): the unit and user are asked for.
    assert p.pushed == [([service.API_CONFIG, "/usr/local/lib/ccrp/api_manager.py"], [service.API_UNIT])]
    assert p.execs == [["sh", "-c", service.HAS_UNIT_SH]]
    # A clone from before the service (no unit, agent or user): one line saying what to do.
    with pytest.raises(CcrpError) as err:
        service.apply_api_manager(Recorder(rc=1), "nao1", files, {})
    assert "older snapshot" in err.value.one_line() and "snapshot build" in err.value.hint
    have = {f.dest: hashlib.sha256(f.content.encode()).hexdigest() for f in files}
    p = Recorder()
    service.apply_api_manager(p, "nao1", files, have)  # unchanged (a snapshot's agent is the same file): left alone
    assert p.pushed == [] and p.execs == []
    service.apply_api_manager(p, "nao1", [], have)  # turned off: removed and stopped
    assert p.execs == [["sh", "-c", service.OFF_SH]] and "systemctl stop ccrp-api-manager.service" in service.OFF_SH
    p = Recorder()
    service.apply_api_manager(p, "nao1", [], {})  # off and absent: nothing to do
    assert p.pushed == [] and p.execs == []


def test_on_a_jazzy_fleet_fleet_up_pushes_the_agent_and_its_rclpy_side_with_the_config():
    """A ROS 2 clone's image holds no agents: the API manager comes with its config (so a bare
    cloud clone's user-data stays under AWS's limit), and a changed agent restarts it."""
    import hashlib

    fleet = inv(ros={"distro": "jazzy"}, services={"api_manager": {"backend": "face-recognition"}})
    files = service.api_manager_files(fleet, fleet.robots[0])
    dests = [f.dest for f in files]
    assert dests == [service.API_CONFIG, "/usr/local/lib/ccrp/api_manager.py", "/usr/local/lib/ccrp/api_manager_ros2.py"]
    assert "from api_manager_ros2 import Ros2" in files[1].content and "import rclpy" in files[2].content
    p = Recorder()
    service.apply_api_manager(p, "nao1", files, {})
    # Asks for the unit and user only: the agent is in the push.
    assert p.pushed == [(dests, [service.API_UNIT])] and p.execs == [["sh", "-c", service.HAS_UNIT_SH]]
    have = {f.dest: hashlib.sha256(f.content.encode()).hexdigest() for f in files}
    service.apply_api_manager(p := Recorder(), "nao1", files, have)
    assert p.pushed == []
    have["/usr/local/lib/ccrp/api_manager_ros2.py"] = "0" * 64  # an older agent there
    service.apply_api_manager(p, "nao1", files, have)
    assert p.pushed == [(dests, [service.API_UNIT])]
    # Noetic's agent goes too (a snapshot's copy is the same file: not sent again when current).
    noetic = inv(services={"api_manager": {}})
    assert [f.dest for f in service.api_manager_files(noetic, noetic.robots[0])] == [
        service.API_CONFIG, "/usr/local/lib/ccrp/api_manager.py"]


def test_status_row():
    fleet = inv(services={"api_manager": {"backend": "opencv"}})
    robot = fleet.robots[0]
    health = {"api_manager": {"running": True, "calls": 7, "errors": 2, "published": 5, "last_latency_ms": 41.5}}
    assert service.api_manager_row(fleet, robot, health) == {
        "running": True, "backend": "opencv", "calls": 7, "errors": 2, "published": 5, "last_latency_ms": 41.5,
        "last_error": None}
    assert service.api_manager_row(fleet, robot, None)["running"] is False
    assert service.api_manager_row(inv(), robot, health) is None


# -- the agent: results and errors ---------------------------------------------------------------

def test_best_match_keeps_those_at_or_above_the_threshold():
    matches = [{"label": "face", "confidence": 0.62, "box": [1, 2, 3, 4]}, {"label": "Person", "confidence": 0.41},
               {"label": "Face", "confidence": 0.97, "box": None}, {"label": "odd", "confidence": None}]
    assert agent.best_match(matches, 0.5)["label"] == "Face"
    assert agent.best_match(matches, 0.97)["label"] == "Face"  # at the threshold is kept
    assert agent.best_match(matches, 0.98) is None
    assert agent.best_match([], 0.0) is None
    assert agent.best_match(matches[:2], 0.6) == matches[0]


def test_opencv_confidence_mapping():
    assert agent.logistic(0) == 0.5
    assert round(agent.logistic(2), 2) == 0.88 and agent.logistic(-3) < 0.05 and agent.logistic(8) > 0.999


def test_result_json():
    out = json.loads(agent.result_json({"label": "face", "confidence": 0.9, "box": [1, 2, 3, 4]}, "opencv", 41.2,
                                       12.5, 320, 240))
    assert out == {"label": "face", "confidence": 0.9, "box": [1, 2, 3, 4], "backend": "opencv", "latency_ms": 41.2,
                   "stamp": 12.5, "width": 320, "height": 240}


def test_errors_are_classified():
    from google.api_core import exceptions as g

    kinds = {
        TimeoutError("t"): "timeout", g.DeadlineExceeded("d"): "timeout", g.TooManyRequests("q"): "quota",
        g.ResourceExhausted("q"): "quota", g.ServiceUnavailable("o"): "outage", g.InternalServerError("o"): "outage",
        ConnectionRefusedError("c"): "outage", g.PermissionDenied("p"): "error", ValueError("v"): "error",
    }
    import requests

    kinds[requests.exceptions.ReadTimeout("r")] = "timeout"
    kinds[requests.exceptions.ConnectionError("c")] = "outage"
    for exc, kind in kinds.items():
        err = agent.classify(exc)
        assert err.kind == kind, exc
        assert err.retryable == (kind != "error")


class Flaky:
    """A backend that raises the queued errors first."""

    def __init__(self, errors):
        self.errors, self.calls = list(errors), 0

    def detect(self, image):
        self.calls += 1
        if self.errors:
            raise self.errors.pop(0)
        return [{"label": "face", "confidence": 0.9, "box": [0, 0, 1, 1]}]


def test_retries_with_backoff_count_and_give_up():
    slept = []
    stats = agent.Stats("flaky")
    caller = agent.Caller(Flaky([TimeoutError(), ConnectionError()]), stats, {"attempts": 3, "base": 0.5, "max": 30},
                          sleep=lambda s: slept.append(s) or False)
    matches, ms = caller.call(None)
    assert matches and ms is not None
    assert (stats.calls, stats.errors, stats.retries, stats.given_up) == (3, 2, 2, 0)
    assert stats.kinds == {"timeout": 1, "outage": 1}
    assert 0.25 <= slept[0] <= 0.5 and 0.5 <= slept[1] <= 1.0  # doubling, half of it jittered
    # An outage longer than the attempts: the frame is given up, and the next waits longer.
    caller.backend = Flaky([ConnectionError()] * 3)
    assert caller.call(None) == (None, None)
    assert (stats.errors, stats.given_up, caller.failures) == (5, 1, 1) and caller.cooldown() >= 1.0
    assert caller.call(None)[0]  # recovered
    assert caller.failures == 0 and caller.cooldown() == 0
    # A refused call (bad key, a plugin's bug) is not retried.
    caller.backend = Flaky([ValueError("bad")])
    assert caller.call(None) == (None, None) and caller.backend.calls == 1
    assert stats.kinds["error"] == 1 and "bad" in stats.last_error
    snap = stats.snapshot()
    assert snap["errors"] == 6 and snap["calls"] == 8 and snap["backend"] == "flaky"


def test_a_plugin_backend_from_its_entry_point(tmp_path, monkeypatch):
    (tmp_path / "ccrp_test_plugin.py").write_text(
        "class Backend:\n"
        "    def __init__(self, cfg):\n        self.cfg = cfg\n"
        "    def detect(self, image):\n        return [{'label': self.cfg['options']['say'], 'confidence': 1.0}]\n")
    dist = tmp_path / "ccrp_test_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: ccrp-test-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[ccrp.api_backends]\nechoer = ccrp_test_plugin:Backend\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    backend = agent.load_backend({"backend": "echoer", "options": {"say": "hello"}})
    assert backend.detect(None) == [{"label": "hello", "confidence": 1.0}]
    with pytest.raises(agent.BackendError, match="no backend 'nothere'"):
        agent.load_backend({"backend": "nothere"})
    monkeypatch.delitem(sys.modules, "ccrp_test_plugin", raising=False)


# -- the agent: backends -------------------------------------------------------------------------

def face_image():
    """A 320x240 photograph with a face: Grace Hopper, shipped by matplotlib (its sample data)."""
    cv2 = pytest.importorskip("cv2")
    mpl = pytest.importorskip("matplotlib")
    img = cv2.imread(str(Path(mpl.get_data_path()) / "sample_data" / "grace_hopper.jpg"))
    return cv2.resize(img[:384], (320, 240))  # the top 4:3 of the 512x600 portrait


def test_opencv_finds_the_face_and_nothing_in_a_blank_image():
    import numpy as np

    img = face_image()
    backend = agent.OpenCvBackend({})
    best = agent.best_match(backend.detect(img), 0.5)
    assert best["label"] == "face" and best["confidence"] > 0.8
    x, y, w, h = best["box"]
    assert 60 < x < 140 and 30 < y < 100 and 100 < w < 180  # her face, not the uniform
    assert backend.detect(np.full((240, 320, 3), 128, np.uint8)) == []


def test_face_recognition_names_a_face_learned_through_the_dataset_and_forgets_it_with_it(tmp_path):
    """The thesis's case study on one clone: an unlearned face is "unknown"; once an image of the
    person is in the `faces` dataset (knowledge sync puts it there from another clone) the same face
    in another frame is named; a second person's image does not take the name; deleting the
    image (a tombstone from another clone) makes the face unknown again."""
    cv2 = pytest.importorskip("cv2")
    import numpy as np

    portrait = cv2.imread(str(Path(pytest.importorskip("matplotlib").get_data_path()) / "sample_data" / "grace_hopper.jpg"))
    files = tmp_path / "faces" / "files"
    files.mkdir(parents=True)
    backend = agent.FaceRecognitionBackend({"options": {"knowledge_root": str(tmp_path)}})
    frame = face_image()

    def seen():
        backend.checked = 0.0  # the 2 s rescan, now
        return [(m["label"], m["distance"] is not None) for m in backend.detect(frame)]

    assert seen() == [("unknown", False)]
    assert backend.detect(np.full((240, 320, 3), 128, np.uint8)) == []
    # Another crop and scale of the portrait than the camera frame, as a person's photo would be.
    cv2.imwrite(str(files / "grace.png"), cv2.resize(portrait[20:420, 30:560], (400, 300)))
    noise = (np.random.default_rng(1).random((120, 120)) * 255).astype(np.uint8)
    cv2.imwrite(str(files / "someone-2.png"), noise)
    assert seen() == [("grace", True)]
    (files / "grace.png").unlink()
    assert seen() == [("unknown", True)]  # only someone's image is left, too far from her face
    assert [agent.person_of(n) for n in ("alice.png", "alice-2.jpg", "alice.nao2-1a2b3c4d.png", "bob-x.png")] == \
        ["alice", "alice", "alice", "bob-x"]
    match = backend.detect(frame)[0]
    assert json.loads(agent.result_json(match, "face-recognition", 1.0, 0.0, 320, 240))["distance"] == match["distance"]


def test_image_messages_are_converted():
    import numpy as np

    class Msg:
        def __init__(self, encoding, data, width, height, step):
            self.encoding, self.data, self.width, self.height, self.step = encoding, data, width, height, step

    rgb = np.zeros((2, 3, 3), np.uint8)
    rgb[..., 0] = 200  # red
    padded = np.zeros((2, 12), np.uint8)  # rows padded to 12 bytes
    padded[:, :9] = rgb.reshape(2, 9)
    bgr = agent.image_to_bgr(Msg("rgb8", padded.tobytes(), 3, 2, 12))
    assert bgr.shape == (2, 3, 3) and (bgr[..., 2] == 200).all() and (bgr[..., 0] == 0).all()
    mono = agent.image_to_bgr(Msg("mono8", bytes([7] * 6), 3, 2, 3))
    assert mono.shape == (2, 3, 3) and (mono == 7).all()
    with pytest.raises(ValueError, match="16UC1"):
        agent.image_to_bgr(Msg("16UC1", b"", 1, 1, 2))


def google_backend(vision: FakeVision, tmp_path, timeout=2.0):
    key = tmp_path / "key.json"
    key.write_text(json.dumps(vision.service_account()))
    return agent.GoogleVisionBackend({"google_vision": {"endpoint": vision.url, "timeout": timeout,
                                                        "credentials": str(key)}})


def test_google_vision_against_a_local_rest_endpoint(tmp_path):
    pytest.importorskip("google.cloud.vision")
    img = face_image()
    with FakeVision() as vision:
        backend = google_backend(vision, tmp_path)
        matches = backend.detect(img)
        assert matches[0] == {"label": "face", "confidence": 0.93, "box": [97, 64, 140, 140]}
        assert {m["label"] for m in matches} == {"face", "Face", "Person"}
        assert agent.best_match(matches, 0.95)["label"] == "Face"
        assert agent.best_match(matches, 0.99) is None
        req = vision.requests[0]["requests"][0]
        assert {f["type"] for f in req["features"]} in ({"FACE_DETECTION", "LABEL_DETECTION"}, {1, 4})
        assert vision.jwts == 1  # authorized by a JWT the key signed


def test_google_vision_outage_quota_and_timeout_are_retried_and_counted(tmp_path):
    pytest.importorskip("google.cloud.vision")
    img = face_image()
    with FakeVision(hang_s=1.5) as vision:
        stats = agent.Stats("google-vision")
        caller = agent.Caller(google_backend(vision, tmp_path, timeout=0.5), stats,
                              {"attempts": 4, "base": 0.05, "max": 0.2})
        vision.fail[:] = [503, 429, "hang"]
        matches, ms = caller.call(img)
        assert matches and matches[0]["label"] == "face"
        assert stats.kinds == {"outage": 1, "quota": 1, "timeout": 1}
        assert (stats.calls, stats.errors, stats.retries, stats.given_up) == (4, 3, 3, 0)
        assert stats.last_latency_ms == ms and ms < 1500
        # An outage longer than the attempts: given up, counted, and the service goes on.
        vision.fail[:] = [503] * 4
        assert caller.call(img) == (None, None)
        assert stats.given_up == 1 and stats.kinds["outage"] == 5 and "503" in stats.last_error
        assert caller.call(img)[0]


def test_google_vision_without_its_key_is_counted_not_fatal(tmp_path):
    pytest.importorskip("google.cloud.vision")
    stats = agent.Stats("google-vision")
    backend = agent.GoogleVisionBackend({"google_vision": {"endpoint": "http://127.0.0.1:9", "timeout": 1,
                                                           "credentials": str(tmp_path / "absent.json")}})
    caller = agent.Caller(backend, stats, {"attempts": 2, "base": 0.01})
    assert caller.call(face_image()) == (None, None)
    assert stats.kinds == {"error": 1} and "ccrp fleet up pushes them" in stats.last_error


def test_status_table_cell():
    from ccrp_cli.cli.status import api_cell
    from ccrp_cli.models.status import ApiManager

    row = {"running": True, "backend": "opencv", "calls": 12, "errors": 1, "last_latency_ms": 38.9}
    assert api_cell(ApiManager(**row)) == "opencv: 12 calls, 1 errors, last 38.9 ms"
    assert api_cell(ApiManager(**{**row, "running": False})) == "opencv: not running"
    assert api_cell(None) == "-"


def test_a_frame_goes_to_the_backend_and_the_best_match_is_published():
    """Service.step, without ROS: a backend that cannot load is counted and tried again later; a
    frame's best match is published as JSON through the ROS side (ROS 1's, or ROS 2's with its
    sec/nanosec stamp); nothing is published under the threshold."""
    import threading
    import time
    from types import SimpleNamespace

    from ccrp_cli.agent import api_manager_ros2

    published = []
    svc = agent.Service.__new__(agent.Service)
    svc.cfg = {"backend": "flaky", "min_confidence": 0.5, "retry": {"attempts": 1}}
    svc.stats, svc.stop = agent.Stats("flaky"), threading.Event()
    svc.backend = svc.caller = None
    svc.next_call, svc.load_failures = 0.0, 0
    svc.ros = SimpleNamespace(publish=published.append, stamp=agent.Ros1.stamp)
    frame = SimpleNamespace(encoding="mono8", data=bytes(6), width=3, height=2, step=3,
                            header=SimpleNamespace(stamp=SimpleNamespace(to_sec=lambda: 12.5)))
    svc.step(frame)  # no backend "flaky": counted as a load error, next try in 2 s
    assert svc.stats.kinds == {"load": 1} and svc.next_call > time.monotonic() + 1 and published == []
    svc.backend = Flaky([])
    svc.caller = agent.Caller(svc.backend, svc.stats, svc.cfg["retry"])
    svc.step(frame)
    assert json.loads(published[0]) == {"label": "face", "confidence": 0.9, "box": [0, 0, 1, 1], "backend": "flaky",
                                        "latency_ms": json.loads(published[0])["latency_ms"], "stamp": 12.5,
                                        "width": 3, "height": 2}
    # A ROS 2 image: its data an array of bytes, its stamp in sec and nanosec.
    import array

    svc.ros = SimpleNamespace(publish=published.append, stamp=api_manager_ros2.Ros2.stamp)
    frame2 = SimpleNamespace(encoding="rgb8", data=array.array("B", bytes(18)), width=3, height=2, step=9,
                             header=SimpleNamespace(stamp=SimpleNamespace(sec=12, nanosec=750_000_000)))
    svc.step(frame2)
    assert json.loads(published[1])["stamp"] == 12.75 and svc.stats.published == 2
    svc.cfg["min_confidence"] = 0.95
    svc.step(frame)
    assert len(published) == 2 and svc.stats.published == 2
