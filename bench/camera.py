"""The camera view's reads on Docker (`ccrp robot camera`, the dashboard's Camera): a read that
finds no camera agent on the clone (it starts the agent: a ROS node, OpenCV, the first frame) beside
reads the running agent answers (one exec, one JPEG encode), in the same run, for a ROS 1 and a
ROS 2 fleet.

Each fleet is one clone (nao1) and its simulated robot (320x240 rgb8 at 5 Hz). `read_ms` is what
`ccrp robot camera --json` reports: from the exec's start to the answer, on the operator's side.
Cold reads stop the agent first (`systemctl stop ccrp-camera` on the clone); warm reads follow
each other. The benchmark brings up its own fleet (own subnets and CCRP_HOME) and removes
everything at the end.

Run: .venv/bin/python bench/camera.py [--cold 5] [--warm 20] [--distros noetic,jazzy]
Writes bench/results/camera.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from docker_fleet import RESULTS, Cli, cleanup_fleet  # noqa: E402

FLEET = "camerabench"


def inventory(distro: str) -> dict:
    return {"fleet": FLEET, "provider": {"kind": "docker", "public_cidr": "172.27.1.0/24"}, "ros": {"distro": distro},
            "vpn": {"pool": "10.86.0.0/16"}, "common": {"cidr": "10.96.0.0/24"}, "robots": [{"name": "nao1"}]}


def stats(values: list[float]) -> dict:
    ordered = sorted(values)
    return {"n": len(ordered), "p50_ms": round(statistics.median(ordered), 1), "min_ms": round(ordered[0], 1),
            "max_ms": round(ordered[-1], 1), "all_ms": [round(v, 1) for v in values]}


def run(args, distro: str) -> dict:
    import docker

    client = docker.from_env(timeout=600)
    with tempfile.TemporaryDirectory() as tmp:
        home, inv, out = Path(tmp) / "home", Path(tmp) / "camera.yaml", Path(tmp) / "frame.jpg"
        inv.write_text(yaml.safe_dump(inventory(distro), sort_keys=False))
        cli = Cli(home, inv)
        try:
            cli("vpn", "init")
            cli("snapshot", "build")
            cli("fleet", "up", "--json")
            cli("robot", "sim", "--robot", "nao1", "--wait", "120", "--json")
            clone = client.containers.get(f"ccrp-{FLEET}-cri-nao1")
            read = lambda: cli("robot", "camera", "--robot", "nao1", "--out", str(out), "--timeout", "10", "--json")[1]  # noqa: E731
            cold, warm = [], []
            for _ in range(args.cold):
                clone.exec_run(["systemctl", "stop", "ccrp-camera"])
                cold.append(read()["read_ms"])
                warm += [read()["read_ms"] for _ in range(args.warm // args.cold)]
        finally:
            try:
                cli("fleet", "down")
            finally:
                cleanup_fleet(FLEET)
    result = {"distro": distro, "cold": stats(cold), "warm": stats(warm)}
    result["cold_over_warm_p50"] = round(result["cold"]["p50_ms"] / result["warm"]["p50_ms"], 1)
    print(f"bench: {distro}: cold p50 {result['cold']['p50_ms']} ms, warm p50 {result['warm']['p50_ms']} ms",
          file=sys.stderr)
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cold", type=int, default=5)
    ap.add_argument("--warm", type=int, default=20)
    ap.add_argument("--distros", default="noetic,jazzy")
    args = ap.parse_args()
    result = {
        "benchmark": "camera",
        "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release()},
        "distros": {d: run(args, d) for d in args.distros.split(",")},
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "camera.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({d: {k: r[k] for k in ("cold", "warm", "cold_over_warm_p50")} for d, r in result["distros"].items()},
                     indent=1))


if __name__ == "__main__":
    main()
