#!/usr/bin/python3
"""ccrp API manager: runs ON a clone (system python3 + rospy + cv2, or on a ROS 2 clone rclpy and cv2
from the distro's venv, which ros-run puts on the path, with api_manager_ros2.py beside this file;
nothing from ccrp).

Subscribes to the robot's camera topic (sensor_msgs/Image), sends at most `rate` images a second
to a detection backend, drops the matches under `min_confidence` and publishes the best one on the
output topic as JSON in a std_msgs/String:

    {"label": "face", "confidence": 0.93, "box": [x, y, w, h], "backend": "opencv",
     "latency_ms": 41.2, "stamp": 1700000000.5, "width": 320, "height": 240}

Backends (docs/services.md):
  opencv         offline face detection with the Haar cascade OpenCV ships (no account needed)
  face-recognition  opencv's faces, each recognised (LBPH, OpenCV contrib) against the images of a
                 knowledge dataset named after their person: label is the person or "unknown"
  google-vision  the official google-cloud-vision client, REST transport, at a configurable
                 endpoint, with a service-account key pushed into the clone's secrets
  <plugin>       an entry point of group `ccrp.api_backends`: a callable taking the config dict
                 and returning an object with detect(image_bgr) -> [{label, confidence, box}]

A failed call (timeout, quota, outage, or anything a plugin raises) is counted and retried with
exponential backoff; after the last attempt the frame is given up and the next call waits for a
backoff that grows with consecutive failures. Nothing a backend does stops the service. The agent
writes its counters to a status file every second for `ccrp status`.
"""

from __future__ import annotations

import json
import math
import os
import random
import sys
import threading
import time

DEFAULT_CONFIG = "/etc/ccrp/api_manager.json"
# Where OpenCV's packages put their Haar cascades: the PyPI wheels inside cv2 (cv2.data), Debian's
# opencv-data under /usr/share.
CASCADE = "haarcascade_frontalface_default.xml"
CASCADE_DIRS = ("/usr/share/opencv4/haarcascades", "/usr/share/opencv/haarcascades")
ENTRY_POINT_GROUP = "ccrp.api_backends"


def log(msg: str) -> None:
    print(f"ccrp-api-manager: {msg}", file=sys.stderr, flush=True)


# -- results ------------------------------------------------------------------------------------

def best_match(matches: list[dict], min_confidence: float) -> dict | None:
    """The match of highest confidence among those at or above min_confidence, or None."""
    kept = [m for m in matches if m.get("confidence") is not None and m["confidence"] >= min_confidence]
    return max(kept, key=lambda m: m["confidence"]) if kept else None


def logistic(weight: float) -> float:
    """OpenCV's cascade score -> a confidence in (0, 1). detectMultiScale3's levelWeights is the
    margin of a detection's last stage (its summed weak classifiers minus the stage threshold), so
    0 is a window that barely passed: 0.5; 2 -> 0.88; 4 -> 0.98."""
    return 1.0 / (1.0 + math.exp(-weight))


# -- errors -------------------------------------------------------------------------------------

class BackendError(Exception):
    """A failed call. `kind`: timeout | quota | outage (retried) or error (not retried: bad
    credentials, a refused request, a backend's own bug)."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind

    @property
    def retryable(self) -> bool:
        return self.kind in ("timeout", "quota", "outage")


def classify(exc: BaseException) -> BackendError:
    """Any exception a backend raised as a BackendError of a kind."""
    if isinstance(exc, BackendError):
        return exc
    name = type(exc).__name__
    text = f"{name}: {exc}"[:300]
    if getattr(exc, "retryable", None) is True:
        return BackendError("outage", text)
    if isinstance(exc, TimeoutError) or "Timeout" in name or name == "DeadlineExceeded":
        return BackendError("timeout", text)
    code = getattr(exc, "code", None)  # google.api_core's HTTP status of the failed call
    code = getattr(code, "value", code)
    if name in ("TooManyRequests", "ResourceExhausted") or code == 429:
        return BackendError("quota", text)
    if isinstance(exc, ConnectionError) or name in (
            "ServiceUnavailable", "InternalServerError", "BadGateway", "GatewayTimeout", "ServerError",
            "TransportError", "ConnectionError", "RetryError") or (isinstance(code, int) and code >= 500):
        return BackendError("outage", text)
    return BackendError("error", text)


# -- images -------------------------------------------------------------------------------------

def image_to_bgr(msg):
    """A sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8) as an HxWx3 uint8 BGR array."""
    import numpy as np

    channels = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}.get(msg.encoding)
    if channels is None:
        raise ValueError(f"unsupported image encoding {msg.encoding!r}")
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    rows = buf[: msg.height * msg.step].reshape(msg.height, msg.step)
    img = rows[:, : msg.width * channels].reshape(msg.height, msg.width, channels)
    if msg.encoding == "mono8":
        return np.repeat(img, 3, axis=2)
    if msg.encoding in ("rgb8", "rgba8"):
        return np.ascontiguousarray(img[:, :, 2::-1])
    return np.ascontiguousarray(img[:, :, :3])


# -- backends -----------------------------------------------------------------------------------

def cascade_path() -> str:
    import cv2

    dirs = [getattr(getattr(cv2, "data", None), "haarcascades", ""), *CASCADE_DIRS]
    for d in dirs:
        if d and os.path.exists(os.path.join(d, CASCADE)):
            return os.path.join(d, CASCADE)
    raise FileNotFoundError(f"no {CASCADE} in {', '.join(d for d in dirs if d)}")


class OpenCvBackend:
    """Faces, offline: the Haar cascade OpenCV ships, confidence from detectMultiScale3's
    levelWeights through logistic()."""

    name = "opencv"

    def __init__(self, cfg: dict) -> None:
        import cv2

        self.cv2 = cv2
        self.cascade = cv2.CascadeClassifier(cascade_path())
        opts = cfg.get("options") or {}
        self.scale = float(opts.get("scale_factor", 1.1))
        self.neighbors = int(opts.get("min_neighbors", 5))
        self.min_size = int(opts.get("min_size", 24))

    def detect(self, image) -> list[dict]:
        cv2 = self.cv2
        gray = cv2.equalizeHist(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        rects, _levels, weights = self.cascade.detectMultiScale3(
            gray, scaleFactor=self.scale, minNeighbors=self.neighbors, minSize=(self.min_size, self.min_size),
            outputRejectLevels=True)
        return [{"label": "face", "confidence": round(logistic(float(w)), 4), "box": [int(v) for v in r]}
                for r, w in zip(rects, weights)]


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".bmp")
FACE_SIZE = (100, 100)


def person_of(filename: str) -> str:
    """The person a training image shows: its name up to the first dot, without a trailing -N
    (alice.png, alice-2.jpg -> alice; a name two clones gave other content keeps its stem:
    alice.nao2-1a2b3c4d.png -> alice)."""
    stem = filename.split(".", 1)[0]
    base, dash, tail = stem.rpartition("-")
    return base if dash and base and tail.isdigit() else stem


class FaceRecognitionBackend:
    """The thesis's face recognition (chapter 9): faces found as by `opencv`, each recognised with
    OpenCV contrib's LBPH recogniser trained on a knowledge dataset (by default `faces`: images
    named after the person, shared between clones by knowledge sync), so a face learned on one
    clone is recognised on every clone sharing the dataset. label: the person, or "unknown"."""

    name = "face-recognition"

    def __init__(self, cfg: dict) -> None:
        import cv2

        if not hasattr(cv2, "face"):
            raise BackendError("error", "this OpenCV has no cv2.face (opencv-contrib-python is needed)")
        self.cv2 = cv2
        self.detector = OpenCvBackend(cfg)
        opts = cfg.get("options") or {}
        root = str(opts.get("knowledge_root", "/var/lib/ccrp/knowledge"))
        self.files = os.path.join(root, str(opts.get("dataset", "faces")), "files")
        # LBPH's distance (chi-square of the histograms): at or under it, the face is that person.
        self.threshold = float(opts.get("threshold", 80.0))
        self.recognizer, self.people, self.seen, self.checked = None, [], None, 0.0

    def _face(self, gray, box=None):
        cv2 = self.cv2
        if box is None:
            found = self.detector.cascade.detectMultiScale(gray, scaleFactor=self.detector.scale,
                                                          minNeighbors=self.detector.neighbors)
            box = max(found, key=lambda r: r[2] * r[3]) if len(found) else (0, 0, gray.shape[1], gray.shape[0])
        x, y, w, h = (int(v) for v in box)
        return cv2.resize(gray[y:y + h, x:x + w], FACE_SIZE)

    def _train(self) -> None:
        """Train again when the dataset's files changed (checked at most every 2 s): a face
        learned on another clone is used within a frame or two of its arrival."""
        now = time.monotonic()
        if now - self.checked < 2.0 and self.seen is not None:
            return
        self.checked = now
        try:
            names = sorted(n for n in os.listdir(self.files) if n.lower().endswith(IMAGE_SUFFIXES))
            listing = [(n, os.stat(os.path.join(self.files, n)).st_mtime_ns) for n in names]
        except FileNotFoundError:
            names, listing = [], []
        if listing == self.seen:
            return
        import numpy as np

        cv2 = self.cv2
        faces, labels, people = [], [], sorted({person_of(n) for n in names})
        for n in names:
            img = cv2.imread(os.path.join(self.files, n), cv2.IMREAD_GRAYSCALE)
            if img is not None:
                faces.append(self._face(cv2.equalizeHist(img)))
                labels.append(people.index(person_of(n)))
        self.recognizer = None
        if faces:
            self.recognizer = cv2.face.LBPHFaceRecognizer_create()
            self.recognizer.train(faces, np.array(labels, dtype=np.int32))
        self.people, self.seen = people, listing
        log(f"face recognition: {len(faces)} image(s) of {len(people)} person(s) from {self.files}")

    def detect(self, image) -> list[dict]:
        self._train()
        matches = self.detector.detect(image)
        if not matches:
            return []
        gray = self.cv2.equalizeHist(self.cv2.cvtColor(image, self.cv2.COLOR_BGR2GRAY))
        for m in matches:
            m["label"], m["distance"] = "unknown", None
            if self.recognizer is not None:
                label, distance = self.recognizer.predict(self._face(gray, m["box"]))
                m["distance"] = round(float(distance), 1)
                if distance <= self.threshold:
                    m["label"] = self.people[label]
        return matches


def vertices_box(vertices) -> list[int] | None:
    xs, ys = [v.x for v in vertices], [v.y for v in vertices]
    if not xs:
        return None
    return [min(xs), min(ys), max(xs) - min(xs), max(ys) - min(ys)]


class GoogleVisionBackend:
    """Google Cloud Vision's face and label detection through the official client (REST)."""

    name = "google-vision"

    def __init__(self, cfg: dict) -> None:
        import cv2

        self.cv2 = cv2
        g = cfg.get("google_vision") or {}
        self.endpoint, self.timeout, self.credentials = g.get("endpoint"), float(g.get("timeout", 5)), g.get("credentials")
        self.client, self.creds_mtime = None, None

    def _client(self):
        """Made on first use, and again when the pushed key changes (a rotated key, or the tmpfs
        filled again after a reboot)."""
        mtime = os.stat(self.credentials).st_mtime if self.credentials and os.path.exists(self.credentials) else None
        if self.client is None or mtime != self.creds_mtime:
            from google.cloud import vision

            creds = None
            if mtime is not None:
                from google.oauth2 import service_account

                creds = service_account.Credentials.from_service_account_file(
                    self.credentials, scopes=["https://www.googleapis.com/auth/cloud-vision"])
            elif self.credentials:
                raise BackendError("error", f"no credentials at {self.credentials} (ccrp fleet up pushes them)")
            options = {"api_endpoint": self.endpoint} if self.endpoint else None
            self.client = vision.ImageAnnotatorClient(credentials=creds, transport="rest", client_options=options)
            self.creds_mtime = mtime
        return self.client

    def detect(self, image) -> list[dict]:
        from google.cloud import vision

        ok, jpeg = self.cv2.imencode(".jpg", image)
        if not ok:
            raise BackendError("error", "cannot encode the image as JPEG")
        request = vision.AnnotateImageRequest(
            image=vision.Image(content=jpeg.tobytes()),
            features=[vision.Feature(type_=vision.Feature.Type.FACE_DETECTION, max_results=10),
                      vision.Feature(type_=vision.Feature.Type.LABEL_DETECTION, max_results=10)])
        # retry=None: the client's own retries would hide failures from our counters and backoff.
        reply = self._client().batch_annotate_images(requests=[request], timeout=self.timeout, retry=None)
        return matches_of(reply.responses[0])


def matches_of(response) -> list[dict]:
    """An AnnotateImageResponse as matches: faces (label "face", a box) and labels (no box)."""
    if response.error and response.error.code:
        kind = {4: "timeout", 8: "quota", 14: "outage", 13: "outage"}.get(response.error.code, "error")
        raise BackendError(kind, f"Vision error {response.error.code}: {response.error.message}"[:300])
    out = [{"label": "face", "confidence": round(f.detection_confidence, 4), "box": vertices_box(f.bounding_poly.vertices)}
           for f in response.face_annotations]
    out += [{"label": lab.description, "confidence": round(lab.score, 4), "box": None}
            for lab in response.label_annotations]
    return out


BUILTIN = {"opencv": OpenCvBackend, "face-recognition": FaceRecognitionBackend, "google-vision": GoogleVisionBackend}


def load_backend(cfg: dict):
    name = cfg["backend"]
    if name in BUILTIN:
        return BUILTIN[name](cfg)
    from importlib.metadata import entry_points

    found = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == name]
    if not found:
        raise BackendError("error", f"no backend {name!r}: not built in, and no entry point {name!r} in group {ENTRY_POINT_GROUP}")
    return found[0].load()(cfg)


# -- the service --------------------------------------------------------------------------------

class Stats:
    def __init__(self, backend: str) -> None:
        self.lock = threading.Lock()
        self.backend = backend
        self.frames = self.calls = self.errors = self.retries = self.published = self.given_up = 0
        self.kinds: dict[str, int] = {}
        self.last_latency_ms: float | None = None
        self.last_error: str | None = None

    def snapshot(self) -> dict:
        with self.lock:
            return {"time": time.time(), "backend": self.backend, "frames": self.frames, "calls": self.calls,
                    "errors": self.errors, "error_kinds": dict(self.kinds), "retries": self.retries,
                    "given_up": self.given_up, "published": self.published,
                    "last_latency_ms": self.last_latency_ms, "last_error": self.last_error}


class Caller:
    """Calls a backend with retries and backoff, and counts. `sleep` is an Event.wait-like
    function (returns True to stop early)."""

    def __init__(self, backend, stats: Stats, retry: dict | None = None, sleep=None) -> None:
        retry = retry or {}
        self.backend, self.stats = backend, stats
        self.attempts = int(retry.get("attempts", 3))
        self.base, self.cap = float(retry.get("base", 0.5)), float(retry.get("max", 30.0))
        self.sleep = sleep or (lambda s: time.sleep(s) or False)
        self.failures = 0  # consecutive frames given up

    def delay(self, n: int) -> float:
        """Backoff before attempt n+1 (n >= 0): base * 2^n, capped, with full jitter on half."""
        d = min(self.cap, self.base * (2 ** n))
        return d / 2 + random.uniform(0, d / 2)

    def cooldown(self) -> float:
        """How long to wait before the next frame after `failures` frames were given up in a row."""
        return self.delay(self.failures + self.attempts - 1) if self.failures else 0.0

    def call(self, image) -> tuple[list[dict] | None, float | None]:
        """(matches, latency in ms) of the first attempt that succeeded, or (None, None)."""
        for attempt in range(self.attempts):
            t0 = time.monotonic()
            try:
                matches = self.backend.detect(image)
            except Exception as exc:  # noqa: BLE001 - whatever a backend raises, the service goes on
                err = classify(exc)
                with self.stats.lock:
                    self.stats.calls += 1
                    self.stats.errors += 1
                    self.stats.kinds[err.kind] = self.stats.kinds.get(err.kind, 0) + 1
                    self.stats.last_error = f"{err.kind}: {err}"[:300]
                if not err.retryable or attempt == self.attempts - 1:
                    break
                with self.stats.lock:
                    self.stats.retries += 1
                if self.sleep(self.delay(attempt)):
                    break
                continue
            ms = round((time.monotonic() - t0) * 1000, 1)
            with self.stats.lock:
                self.stats.calls += 1
                self.stats.last_latency_ms = ms
            self.failures = 0
            return matches, ms
        with self.stats.lock:
            self.stats.given_up += 1
        self.failures += 1
        return None, None


def result_json(match: dict, backend: str, latency_ms: float, stamp: float, width: int, height: int) -> str:
    out = {"label": match["label"], "confidence": match["confidence"], "box": match.get("box"), "backend": backend,
           "latency_ms": latency_ms, "stamp": stamp, "width": width, "height": height}
    if "distance" in match:  # face-recognition: how far the face is from the person's images
        out["distance"] = match["distance"]
    return json.dumps(out)


def write_atomic(path: str, text: str) -> None:
    tmp = f"{path}.tmp"
    with open(tmp, "w") as fh:
        fh.write(text)
    os.replace(tmp, path)


class Ros1:
    """The rospy side: the robot's images in (on_image), the results out. Built by Service."""

    def __init__(self, cfg: dict, on_image) -> None:
        import rospy
        from sensor_msgs.msg import Image
        from std_msgs.msg import String

        rospy.init_node("ccrp_api_manager", anonymous=False, disable_signals=True)
        self.rospy, self.String = rospy, String
        self.pub = rospy.Publisher(cfg["output"], String, queue_size=10)
        # queue_size=1 and a large buffer: only the newest image matters; older ones are dropped.
        rospy.Subscriber(cfg["input"], Image, on_image, queue_size=1, buff_size=2 ** 24)

    def publish(self, text: str) -> None:
        self.pub.publish(self.String(data=text))

    @staticmethod
    def stamp(msg) -> float:
        return msg.header.stamp.to_sec()

    def ok(self) -> bool:
        return not self.rospy.is_shutdown()

    def close(self) -> None:
        self.rospy.signal_shutdown("stopped")


class Service:
    """The frames, the backend calls and the counters; `ros` (Ros1, or api_manager_ros2.Ros2) is the
    ROS side, made with the service's on_image."""

    def __init__(self, cfg: dict, ros=Ros1) -> None:
        self.cfg = cfg
        self.stats = Stats(cfg["backend"])
        self.stop = threading.Event()
        self.new = threading.Event()
        self.latest = None
        self.backend = None
        self.caller = None
        self.ros = ros(cfg, self.on_image)

    def on_image(self, msg) -> None:
        with self.stats.lock:
            self.stats.frames += 1
        self.latest = msg
        self.new.set()

    def _backend(self):
        """The backend, loaded on first use; a failure to load it is counted and retried."""
        if self.backend is None:
            self.backend = load_backend(self.cfg)
            self.caller = Caller(self.backend, self.stats, self.cfg.get("retry"), self.stop.wait)
        return self.caller

    def run(self) -> None:
        period = 1.0 / float(self.cfg["rate"])
        self.next_call = 0.0
        self.load_failures = 0
        while not self.stop.is_set():
            if not self.new.wait(0.5):
                continue
            wait = self.next_call - time.monotonic()
            if wait > 0 and self.stop.wait(wait):
                return
            self.new.clear()
            self.next_call = time.monotonic() + period
            try:
                self.step(self.latest)
            except Exception as exc:  # noqa: BLE001 - one bad frame (or a publish failing) must not stop the service
                log(f"{type(exc).__name__}: {exc}")
                with self.stats.lock:
                    self.stats.last_error = f"{type(exc).__name__}: {exc}"[:300]

    def step(self, msg) -> None:
        """One frame: to the backend, the best match (if any) published."""
        try:
            caller = self._backend()
            self.load_failures = 0
        except Exception as exc:  # noqa: BLE001 - a backend that cannot load yet (no key pushed)
            err = classify(exc)
            with self.stats.lock:
                self.stats.errors += 1
                self.stats.kinds["load"] = self.stats.kinds.get("load", 0) + 1
                self.stats.last_error = f"load: {err}"[:300]
            self.load_failures += 1
            self.next_call = time.monotonic() + min(30.0, 2 ** self.load_failures)
            return
        image = image_to_bgr(msg)
        matches, ms = caller.call(image)
        self.next_call = max(self.next_call, time.monotonic() + caller.cooldown())
        if matches is None:
            return
        best = best_match(matches, float(self.cfg["min_confidence"]))
        if best is None:
            return
        stamp = self.ros.stamp(msg) or time.time()
        self.ros.publish(result_json(best, self.stats.backend, ms, stamp, msg.width, msg.height))
        with self.stats.lock:
            self.stats.published += 1


def main() -> None:
    path = sys.argv[1] if len(sys.argv) > 1 else DEFAULT_CONFIG
    with open(path) as fh:
        cfg = json.load(fh)
    # A ROS 1 clone's environment names its master (ros.env); a ROS 2 clone's has none, and has
    # api_manager_ros2.py beside this file (docs/services.md).
    if os.environ.get("ROS_MASTER_URI"):
        ros = Ros1
    else:
        from api_manager_ros2 import Ros2 as ros
    service = Service(cfg, ros)
    worker = threading.Thread(target=service.run, name="api-manager", daemon=True)
    worker.start()
    log(f"{cfg['input']} -> {cfg['backend']} at {cfg['rate']} Hz -> {cfg['output']} (min confidence {cfg['min_confidence']})")
    try:
        while service.ros.ok() and worker.is_alive():
            try:
                write_atomic(cfg["status"], json.dumps(service.stats.snapshot()))
            except OSError as exc:
                log(f"status: {exc}")
            time.sleep(1)
    finally:
        service.stop.set()
        worker.join(timeout=5)  # its publish, if it is in one, before the ROS side goes
        service.ros.close()


if __name__ == "__main__":
    main()
