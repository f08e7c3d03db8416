"""The API manager's cost, in a container of a clone image (docs/services.md, Measured).

In one container from IMAGE (a snapshot built by `ccrp snapshot build`; no systemd, a bare
rosmaster): the opencv backend called directly on Grace Hopper's photograph (matplotlib's sample
data) at 320x240 and 640x480, then the same frame sent through the agent (agent/api_manager.py as
the clone runs it: subscribe, rate limit, detect, publish) by a ROS node that times each frame to
its result. Per frame, the round trip less the backend call the agent timed for that frame is the
API manager's overhead over a direct backend call (ROS serialisation both ways, the worker
hand-off, JSON): paired this way, it is not lost in the backend's own spread on a busy host. The
container is removed at the end.

Run: .venv/bin/python bench/api_manager.py IMAGE [--samples 50]
Writes bench/results/api_manager.json.
"""

from __future__ import annotations

import argparse
import io
import json
import platform
import subprocess
import sys
import tarfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"

# In the container: direct calls, then round trips through the agent (rosmaster already up).
PROBE = r"""
import json, statistics, subprocess, sys, threading, time
sys.path.insert(0, "/tmp")
import numpy as np, cv2, rospy
import api_manager as agent
from sensor_msgs.msg import Image
from std_msgs.msg import String

n = int(sys.argv[1])
full = cv2.imread("/tmp/gh.jpg")
frames = {"320x240": cv2.resize(full[:384], (320, 240)), "640x480": cv2.resize(full[:384], (640, 480))}
backend = agent.OpenCvBackend({})

def stats(ms):
    ms = sorted(ms)
    return {"n": len(ms), "p50_ms": round(statistics.median(ms), 1), "p95_ms": round(ms[int(0.95 * (len(ms) - 1))], 1),
            "mean_ms": round(statistics.fmean(ms), 1)}

out = {"direct": {}, "through_agent": {}, "confidence": {}}
for size, img in frames.items():
    backend.detect(img)
    ms = []
    for _ in range(n):
        t0 = time.perf_counter(); m = backend.detect(img); ms.append((time.perf_counter() - t0) * 1000)
    out["direct"][size] = stats(ms)
    out["confidence"][size] = agent.best_match(m, 0.5)

for size, img in frames.items():
    cfg = {"robot": "bench", "input": "/camera/image_raw", "output": "/api_manager/result", "backend": "opencv",
           "rate": 30, "min_confidence": 0.5, "options": {}, "status": f"/tmp/status-{size}.json"}
    json.dump(cfg, open(f"/tmp/cfg-{size}.json", "w"))
    agent_proc = subprocess.Popen([sys.executable, "/tmp/api_manager.py", f"/tmp/cfg-{size}.json"],
                                  stderr=subprocess.DEVNULL)
    try:
        if size == "320x240":
            rospy.init_node("bench", anonymous=True, disable_signals=True)
        got = threading.Event(); rec = {}
        def on(m):
            rec["t"] = time.perf_counter(); rec["r"] = json.loads(m.data); got.set()
        sub = rospy.Subscriber("/api_manager/result", String, on)
        pub = rospy.Publisher("/camera/image_raw", Image, queue_size=1)
        h, w = img.shape[:2]
        msg = Image(height=h, width=w, encoding="bgr8", step=w * 3, data=img.tobytes())
        deadline = time.time() + 60
        while pub.get_num_connections() < 1 or sub.get_num_connections() < 1:
            assert time.time() < deadline, "the agent did not connect"
            time.sleep(0.05)
        rt, inner = [], []
        for i in range(n + 3):
            got.clear()
            time.sleep(0.05)  # past the agent's rate limit (30 Hz)
            t0 = time.perf_counter(); pub.publish(msg)
            if not got.wait(10):
                continue
            if i >= 3:  # the first calls warm up
                rt.append((rec["t"] - t0) * 1000); inner.append(rec["r"]["latency_ms"])
        # The overhead of each frame: its round trip less the backend call the agent timed for it.
        out["through_agent"][size] = {"round_trip": stats(rt), "backend_latency_reported": stats(inner),
                                      "overhead": stats([a - b for a, b in zip(rt, inner)])}
        sub.unregister(); pub.unregister()
    finally:
        agent_proc.terminate(); agent_proc.wait(10)
print(json.dumps(out))
"""


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("image")
    ap.add_argument("--samples", type=int, default=50)
    args = ap.parse_args()
    import matplotlib

    photo = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    name = f"ccrp-bench-apimgr-{int(time.time())}"
    subprocess.run(["docker", "run", "-d", "--rm", "--name", name, "--network", "none", "--entrypoint", "sleep",
                    args.image, "3600"], check=True, capture_output=True)
    try:
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w") as tar:
            for arc, data in (("api_manager.py", (ROOT / "ccrp_cli" / "agent" / "api_manager.py").read_bytes()),
                              ("gh.jpg", photo.read_bytes()), ("probe.py", PROBE.encode())):
                info = tarfile.TarInfo(arc)
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
        subprocess.run(["docker", "cp", "-", f"{name}:/tmp"], input=buf.getvalue(), check=True)
        env = ["-e", "ROS_MASTER_URI=http://127.0.0.1:11311", "-e", "ROS_HOSTNAME=127.0.0.1", "-e", "ROS_HOME=/tmp"]
        subprocess.run(["docker", "exec", "-d", *env, name, "rosmaster", "--core"], check=True)
        time.sleep(2)
        proc = subprocess.run(["docker", "exec", *env, name, "python3", "/tmp/probe.py", str(args.samples)],
                              capture_output=True, text=True, timeout=1200)
        if proc.returncode != 0:
            sys.stderr.write(proc.stderr[-3000:])
            return 1
        result = json.loads(proc.stdout.strip().splitlines()[-1])
    finally:
        subprocess.run(["docker", "rm", "-f", name], capture_output=True)
    result["image"], result["host"] = args.image, {"cpus": subprocess.run(["nproc"], capture_output=True, text=True).stdout.strip(),
                                                   "machine": platform.machine()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "api_manager.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
