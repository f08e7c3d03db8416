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

With --deploy N: `ccrp deploy` of a Python-only change (one line of the example's node) to one
running clone (--robot nao1) and to all N, side by side: each round changes the node, deploys it to
one clone, changes it again and deploys to all N (target: N=10 at most 2x of 1). Each deploy builds
the change once (only the workspace's layer runs) and pushes it to its clones in parallel. The
fleet (N clones of examples/offload/ros2.yaml's software, subnets no Docker network here uses)
is removed at the end, even on failure.

Beside the times, per round: the bytes each clone was sent for the one-line change (deploy's
`sent_bytes`: the files that changed, gzipped, base64) against the whole install space (as a tar,
gzipped, and base64 as pushed: the one kept in the state directory), and once at the end `deploy --canary 1` of one more change to all N (the canary,
then the others) and `deploy --rollback` of all N (no build).

Run: .venv/bin/python bench/workloads.py --deploy 10 [--rounds 3] [--out PATH]
Writes bench/results/workloads_deploy.json.
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
    from ccrp_cli.services.registry import image_agents
    from ccrp_cli.services.workloads import snapshot_software

    fleet = Fleet.open(inventory)
    inv = fleet.inventory
    plat = recipe_platform(inv.ros.distro, "docker")
    software = snapshot_software(inv, fleet.path)
    text = images.dockerfile(fleet.name, inv.ros.distro, images.DEFAULT_BASE, plat, software, agents=image_agents())
    context = images.build_context(plat, distro=inv.ros.distro, software=software, agents=image_agents())  # wheels: from the cache
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


def deploy_json(home: Path, inventory: Path, *args: str) -> tuple[float, list[dict]]:
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "ccrp_cli", "deploy", *args, "--json", "-i", str(inventory)],
                          capture_output=True, text=True, env={**os.environ, "CCRP_HOME": str(home)}, timeout=1800)
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise SystemExit(f"ccrp deploy {' '.join(args)} failed ({proc.returncode}): {proc.stderr[-1500:]}")
    return wall, json.loads(proc.stdout)


def deploy_bench(args) -> dict:
    """--deploy N: one clone vs N, each deploy a fresh one-line change of the node."""
    sys.path[:0] = [str(ROOT), str(ROOT / "bench")]
    from docker_fleet import cleanup_fleet

    from tests.e2e.fleet import free_subnets

    n = args.deploy
    fleet = "bdp" + secrets.token_hex(3)
    tmp = Path(tempfile.mkdtemp(prefix="ccrp-bench-deploy-"))
    home = tmp / "home"
    one, many, up_s, canary, rollback = [], [], None, None, None
    try:
        shutil.copytree(EXAMPLE / "ros2", tmp / "ros2")
        data = yaml.safe_load((EXAMPLE / "ros2.yaml").read_text())
        public, common, pool = free_subnets()
        data |= {"fleet": fleet, "provider": {"kind": "docker", "public_cidr": public}, "common": {"cidr": common},
                 "robots": [{"name": f"nao{i}", "type": "nao"} for i in range(1, n + 1)]}
        data["vpn"]["pool"] = pool
        inventory = tmp / "inventory.yaml"
        inventory.write_text(yaml.safe_dump(data, sort_keys=False))
        ccrp(home, inventory, "vpn", "init")
        ccrp(home, inventory, "snapshot", "build")
        up_s = ccrp(home, inventory, "fleet", "up")
        node = tmp / NODE
        for k in range(args.rounds):
            for target, runs in ((["--robot", "nao1"], one), ([], many)):
                node.write_text(node.read_text() + f"\n# bench round {k} {secrets.token_hex(4)}\n")
                wall, rows = deploy_json(home, inventory, *target)
                assert all(r["action"] == "deployed" for r in rows) and len(rows) == (1 if target else n), rows
                runs.append({"wall_s": round(wall, 1), "clone_s": sorted(round(r["seconds"], 1) for r in rows),
                             "sent_bytes": sorted(r["sent_bytes"] for r in rows), **whole(home, fleet)})
        node.write_text(node.read_text() + f"\n# bench canary {secrets.token_hex(4)}\n")
        wall, rows = deploy_json(home, inventory, "--canary", "1")
        assert all(r["action"] == "deployed" for r in rows), rows
        canary = {"wall_s": round(wall, 1), "canary_s": round(rows[0]["seconds"], 1),
                  "others_s": sorted(round(r["seconds"], 1) for r in rows[1:])}
        wall, rows = deploy_json(home, inventory, "--rollback")
        assert all(r["action"] == "rolled back" for r in rows), rows
        rollback = {"wall_s": round(wall, 1), "clone_s": sorted(round(r["seconds"], 1) for r in rows)}
    finally:
        try:
            ccrp(home, inventory, "fleet", "down")
        except (SystemExit, NameError):
            pass  # what is left carries the fleet's labels: removed below
        cleanup_fleet(fleet)
        shutil.rmtree(tmp, ignore_errors=True)
    med = statistics.median
    one_s, many_s = med(r["wall_s"] for r in one), med(r["wall_s"] for r in many)
    return {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "example": "examples/offload/ros2.yaml (ament_python): a one-line change of scan_to_map.py",
        "clones": n, "rounds": args.rounds, "fleet_up_s": round(up_s, 1) if up_s else None,
        "deploy_1_s": {"median": round(one_s, 1), "runs": one},
        f"deploy_{n}_s": {"median": round(many_s, 1), "runs": many},
        f"ratio_{n}_over_1": round(many_s / one_s, 2),
        f"canary_1_then_{n - 1}_s": canary,
        f"rollback_{n}_s": rollback,
    }


def whole(home: Path, fleet: str) -> dict:
    """The whole install space of the last deploy (the newest the state directory keeps), as a tar,
    gzipped, and base64-encoded as pushed: what each clone would be sent without the delta."""
    import base64
    import gzip

    kept = max((home / fleet / "deploy").glob("*.tgz.b64"), key=lambda p: p.stat().st_mtime)
    pushed = kept.read_bytes()
    gz = base64.b64decode(pushed)
    return {"tar_bytes": len(gzip.decompress(gz)), "gzip_bytes": len(gz), "pushed_bytes": len(pushed)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cold-rounds", type=int, default=1)
    ap.add_argument("--deploy", type=int, metavar="N", help="deploy to 1 clone vs N instead of the snapshot builds")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    if args.deploy:
        result = deploy_bench(args)
        out = args.out or ROOT / "bench" / "results" / "workloads_deploy.json"
        out.write_text(json.dumps(result, indent=2) + "\n")
        print(json.dumps(result, indent=2))
        return
    args.out = args.out or ROOT / "bench" / "results" / "workloads.json"

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
