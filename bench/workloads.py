"""What a change of the robots' own software costs to build (docs/workloads.md), on the Docker
backend with the offloading example (examples/offload/ros2.yaml, an ament_python workspace whose
package.xml pulls the ros-jazzy-nav-msgs wheel):

  changed    `ccrp snapshot build` after a one-line change of the workspace: ccrp's layers and the
             software's pip layer come from Docker's cache, the workspace's layer runs again
  unchanged  `ccrp snapshot build` again with nothing changed: every layer from the cache
  cold       the same Dockerfile and context built with no cache at all (docker build --no-cache):
             what the first build on a new machine costs, ccrp's image included

Medians over --rounds (cold: --cold-rounds). The benchmark works on its own fleet name and
CCRP_HOME and a copy of the workspace, and removes the images it built at the end, even on failure.

Run: .venv/bin/python bench/workloads.py [--rounds 3] [--cold-rounds 1] [--out PATH]
Writes bench/results/workloads.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import secrets
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "offload"
NODE = Path("ros2/ws/src/ccrp_offload/ccrp_offload/scan_to_map.py")


def ccrp(home: Path, inventory: Path, *args: str) -> float:
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "ccrp_cli", *args, "-i", str(inventory)], capture_output=True,
                          text=True, env={**os.environ, "CCRP_HOME": str(home)}, timeout=1800)
    if proc.returncode != 0:
        raise SystemExit(f"ccrp {' '.join(args)} failed: {proc.stderr[-1500:]}")
    return time.monotonic() - t0


def cold_build(inventory: Path) -> float:
    """The snapshot's Dockerfile and context (as snapshot build makes them), with no cache."""
    import docker

    from ccrp_cli.fleet import Fleet
    from ccrp_cli.providers.docker import images
    from ccrp_cli.providers.docker.archive import tar_files
    from ccrp_cli.recipes import platform as recipe_platform
    from ccrp_cli.workloads import snapshot_software

    fleet = Fleet.open(inventory)
    inv = fleet.inventory
    plat = recipe_platform(inv.ros.distro, "docker")
    software = snapshot_software(inv, fleet.path)
    text = images.dockerfile(fleet.name, inv.ros.distro, images.DEFAULT_BASE, plat, software)
    context = images.build_context(plat, distro=inv.ros.distro, software=software)  # wheels: from the cache
    entries = [("Dockerfile", text.encode(), 0o644), *((n, d, 0o644) for n, d in context.items())]
    client = docker.from_env(timeout=1800)
    tag = f"ccrp/{fleet.name}-clone:cold"
    t0 = time.monotonic()
    try:
        for chunk in client.api.build(fileobj=__import__("io").BytesIO(tar_files(entries)), custom_context=True,
                                      tag=tag, nocache=True, rm=True, forcerm=True, decode=True):
            if "error" in chunk:
                raise SystemExit(f"cold build failed: {chunk['error']}")
        return time.monotonic() - t0
    finally:
        try:
            client.images.remove(tag, noprune=False)
        except docker.errors.APIError:
            pass
        client.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cold-rounds", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "workloads.json")
    args = ap.parse_args()

    fleet = "bwl" + secrets.token_hex(3)
    tmp = Path(tempfile.mkdtemp(prefix="ccrp-bench-workloads-"))
    home = tmp / "home"
    try:
        shutil.copytree(EXAMPLE / "ros2", tmp / "ros2")
        data = yaml.safe_load((EXAMPLE / "ros2.yaml").read_text())
        data["fleet"] = fleet
        inventory = tmp / "inventory.yaml"
        inventory.write_text(yaml.safe_dump(data, sort_keys=False))
        ccrp(home, inventory, "vpn", "init")
        first = ccrp(home, inventory, "snapshot", "build")  # ccrp's layers from the machine's cache, the software's anew
        changed, unchanged = [], []
        for k in range(args.rounds):
            node = tmp / NODE
            node.write_text(node.read_text() + f"\n# bench round {k} {secrets.token_hex(4)}\n")
            changed.append(ccrp(home, inventory, "snapshot", "build"))
            unchanged.append(ccrp(home, inventory, "snapshot", "build"))
        cold = [cold_build(inventory) for _ in range(args.cold_rounds)]
    finally:
        import docker

        client = docker.from_env()
        for image in client.images.list(name=f"ccrp/{fleet}-clone"):
            for tag in image.tags:
                client.images.remove(tag)
        client.close()
        shutil.rmtree(tmp, ignore_errors=True)
    med = statistics.median
    result = {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "example": "examples/offload/ros2.yaml (ament_python, ros-jazzy-nav-msgs)",
        "rounds": args.rounds,
        "first_software_build_s": round(first, 1),
        "changed_workspace_s": {"median": round(med(changed), 1), "all": [round(x, 1) for x in changed]},
        "unchanged_s": {"median": round(med(unchanged), 1), "all": [round(x, 1) for x in unchanged]},
        "cold_s": {"median": round(med(cold), 1), "all": [round(x, 1) for x in cold]} if cold else None,
        "cold_over_changed": round(med(cold) / med(changed), 1) if cold else None,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
