"""The Docker backend end to end, timed through the CLI as a user runs it (issue 3's benchmarks).

  ready    time to ready (VPN server up + master answering) of one clone created from the fleet's
           snapshot vs. from a bare snapshot (systemd + cloud-init only) whose cloud-init installs
           the recipe's packages at boot: the thesis's reason for snapshots. Rounds alternate the
           two so machine noise hits both alike.
  scale    `ccrp fleet scale N` from an empty fleet, for each N in --sizes: wall time per size,
           and the ratio to N=1 (target: 10 clones in at most 3x the time of 1).
  connect  `ccrp robot sim --wait`: from starting the simulated robot's container until its VPN
           session is up and its demo node is registered on its clone's master.

Medians over --rounds. The benchmark works on its own fleet (`bench<random>`, subnets no Docker
network of this machine uses, own CCRP_HOME) and removes its containers, networks, volumes and
images at the end, even on failure.

Run: .venv/bin/python bench/docker_fleet.py [--rounds 3] [--bare-rounds 3] [--sizes 1,5,10,20] [--out PATH]
Writes bench/results/docker_fleet.json and bench/results/docker_fleet.png (--out: that JSON
instead, and no figure).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import secrets
import statistics
import string
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
FLEET = "bench" + "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(6))


def inventory() -> dict:
    # Pools no Docker network, route or fleet of this host overlaps: as `ccrp init` picks them.
    from ccrp_cli.ops.init import free, used_networks

    used = used_networks()
    public, common, pool = free("public", used), free("common", used), free("vpn", used)
    return {
        "fleet": FLEET,
        "provider": {"kind": "docker", "public_cidr": public},
        "vpn": {"pool": pool},
        "common": {"cidr": common},
        "robots": [],
        "template": {"prefix": "robot", "max": 50},
    }


class Cli:
    def __init__(self, home: Path, inventory: Path) -> None:
        self.env = {**os.environ, "CCRP_HOME": str(home)}
        self.env.pop("CCRP_INVENTORY", None)
        self.inventory = str(inventory)

    def __call__(self, *args: str, timeout: float = 1800) -> tuple[float, object]:
        """Run `ccrp ARGS -i INVENTORY`; returns (wall seconds, parsed --json output or None)."""
        argv = [sys.executable, "-m", "ccrp_cli", *args, "-i", self.inventory]
        t0 = time.perf_counter()
        proc = subprocess.run(argv, env=self.env, capture_output=True, text=True, timeout=timeout)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            raise SystemExit(f"ccrp {' '.join(args)} failed ({proc.returncode}): {proc.stderr.strip()[-600:]}")
        out = proc.stdout.strip()
        return wall, (json.loads(out) if out.startswith(("[", "{")) else None)


def use_snapshot(home: Path, record: dict) -> None:
    """Point the fleet at one of the two snapshots built up front (no rebuild between rounds)."""
    os.environ["CCRP_HOME"] = str(home)
    from ccrp_cli.store import FleetStore

    store = FleetStore(FLEET)
    with store.lock():
        state = store.load_state()
        state.snapshot = record
        store.save_state(state)


def recorded_snapshot(home: Path) -> dict:
    return json.loads((home / FLEET / "state.json").read_text())["snapshot"]


def one_clone(cli: Cli) -> dict:
    """`fleet scale 1` from zero, and the CPU time the clone's container used to get ready (from
    its cgroup): what N clones booting at once must share on this machine's cores."""
    import docker

    wall, rows = cli("fleet", "scale", "1", "--json")
    stats = docker.from_env().containers.get(f"ccrp-{FLEET}-cri-{rows[0]['robot']}").stats(stream=False)
    cpu = stats["cpu_stats"]["cpu_usage"]["total_usage"] / 1e9
    return {"wall_s": round(wall, 2), "clone_s": rows[0]["seconds"], "clone_cpu_s": round(cpu, 2)}


def cleanup_fleet(fleet: str) -> None:
    """Everything labelled with a bench fleet, whatever state the run ended in."""
    import docker

    client = docker.from_env()
    flt = {"label": f"ccrp-fleet={fleet}"}
    for c in client.containers.list(ignore_removed=True, all=True, filters=flt):
        c.remove(force=True, v=True)
    for n in client.networks.list(filters=flt):
        n.remove()
    for v in client.volumes.list(filters=flt):
        v.remove(force=True)
    for img in client.images.list(filters=flt):
        client.images.remove(img.id, force=True)


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    ready = result["ready"]
    names = ["snapshot", "bare + cloud-init"]
    medians = [ready["snapshot"]["median_s"], ready["bare"]["median_s"]]
    ax1.bar(names, medians, color=["tab:green", "tab:red"])
    for i, m in enumerate(medians):
        ax1.text(i, m, f"{m:.1f} s", ha="center", va="bottom")
    ax1.set_ylabel("time to ready, median (s)")
    ax1.set_title("one clone: VPN up + master answering")
    sizes = [int(n) for n in result["scale"]]
    walls = [result["scale"][str(n)]["median_s"] for n in sizes]
    ax2.plot(sizes, walls, "o-", label="ccrp fleet scale N (median)")
    ax2.plot(sizes, [walls[0] * n for n in sizes], ":", color="grey", label="N x one clone (serial)")
    if "cpu_floor" in result:
        ax2.plot(sizes, [result["cpu_floor"][str(n)] for n in sizes], "--", color="tab:red",
                 label="CPU floor: N x one clone's CPU / cores")
    ax2.axhline(3 * walls[0], color="tab:orange", ls="--", label="target for N=10: 3x one clone")
    ax2.set_ylim(0, max(walls) * 1.6)
    ax2.set_xlabel("clones")
    ax2.set_ylabel("wall time (s)")
    ax2.set_title("fleet scale from zero")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--bare-rounds", type=int, default=3)
    ap.add_argument("--sizes", default="1,5,10,20")
    ap.add_argument("--out", type=Path, help="write the JSON here (and no figure) instead of bench/results/")
    args = ap.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    RESULTS.mkdir(parents=True, exist_ok=True)
    progress = lambda msg: print(f"bench: {msg}", file=sys.stderr, flush=True)  # noqa: E731

    with tempfile.TemporaryDirectory() as tmp:
        home, inv = Path(tmp) / "home", Path(tmp) / "bench.yaml"
        inv.write_text(yaml.safe_dump(inventory()))
        cli = Cli(home, inv)
        try:
            cli("vpn", "init")
            bare_build, bare = None, None
            if args.bare_rounds:  # a bare snapshot only for rounds that use it
                progress("building the bare snapshot")
                _, bare_build = cli("snapshot", "build", "--bare", "--json")
                bare = recorded_snapshot(home)
            progress("building the fleet snapshot")
            _, snap_build = cli("snapshot", "build", "--json")
            snap = recorded_snapshot(home)

            ready: dict[str, list[dict]] = {"snapshot": [], "bare": []}
            connect: list[dict] = []
            for r in range(max(args.rounds, args.bare_rounds)):
                for kind, record in (("snapshot", snap), ("bare", bare)):
                    if r >= (args.rounds if kind == "snapshot" else args.bare_rounds):
                        continue
                    use_snapshot(home, record)
                    sample = one_clone(cli)
                    ready[kind].append(sample)
                    progress(f"round {r + 1}: clone from {kind} ready in {sample['clone_s']:.1f} s")
                    if kind == "snapshot":
                        _, sim = cli("robot", "sim", "--robot", "robot1", "--wait", "120", "--json")
                        connect.append({"seconds": sim["seconds"], "nodes": sim["nodes"]})
                        progress(f"round {r + 1}: robot connected in {sim['seconds']:.1f} s")
                        cli("robot", "sim", "--robot", "robot1", "--stop")
                    cli("fleet", "scale", "0")

            use_snapshot(home, snap)
            scale: dict[str, list[float]] = {str(n): [] for n in sizes}
            for r in range(args.rounds):
                for n in sizes:
                    wall, rows = cli("fleet", "scale", str(n), "--json")
                    assert sum(row["action"] == "created" for row in rows) == n, rows
                    scale[str(n)].append(round(wall, 2))
                    progress(f"round {r + 1}: fleet scale {n}: {wall:.1f} s")
                    cli("fleet", "scale", "0")
        finally:
            try:
                cli("fleet", "down")
            finally:
                cleanup_fleet(FLEET)

    # What had no round (--bare-rounds 0, --rounds 0) is left out of the results.
    med = lambda xs: round(statistics.median(xs), 2)  # noqa: E731
    result = {
        "benchmark": "docker_fleet",
        "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release()},
        "rounds": args.rounds,
        "bare_rounds": args.bare_rounds,
        "snapshot_images_mb": {"snapshot": snap_build[0]["size_mb"]} | ({"bare": bare_build[0]["size_mb"]} if bare_build else {}),
        "ready": {
            kind: {"median_s": med([s["clone_s"] for s in samples]),
                   "wall_median_s": med([s["wall_s"] for s in samples]), "samples": samples}
            for kind, samples in ready.items() if samples
        },
    }
    if connect:
        result["connect"] = {"median_s": med([c["seconds"] for c in connect]), "samples": connect}
    if args.rounds:
        one = med(scale[str(sizes[0])])
        result["scale"] = {str(n): {"median_s": med(scale[str(n)]), "ratio_to_1": round(med(scale[str(n)]) / one, 2),
                                    "samples": scale[str(n)]} for n in sizes}
    if ready["snapshot"]:
        cpu = med([s["clone_cpu_s"] for s in ready["snapshot"]])
        result["cpu_floor"] = {
            "clone_cpu_s": cpu,
            "note": "CPU seconds one clone's container uses to get ready; N clones need at least N * that / cores",
            **{str(n): round(n * cpu / (os.cpu_count() or 1), 1) for n in sizes},
        }
    if ready["snapshot"] and ready["bare"]:
        result["ready"]["bare_over_snapshot"] = round(result["ready"]["bare"]["median_s"] / result["ready"]["snapshot"]["median_s"], 1)
    (args.out or RESULTS / "docker_fleet.json").write_text(json.dumps(result, indent=2) + "\n")
    if not args.out and "scale" in result and {"snapshot", "bare"} <= result["ready"].keys():
        plot(result, RESULTS / "docker_fleet.png")
    print(json.dumps({k: result[k] for k in ("ready", "connect", "scale") if k in result}, indent=1)[:3000])


if __name__ == "__main__":
    main()
