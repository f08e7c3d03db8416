"""Issue certificates and render everything for a fleet of 100 and of 1,000 robots, in one process.

Phases (fresh CCRP_HOME per repetition, median of --repeat runs; the sizes alternate within each
repetition, so machine noise hits them alike):
  init    Fleet.open of a 100-robot inventory + vpn.init (CA, CRL, address slots)
  issue   what `fleet up` issues (PkiStore.issue_fleet): client, server and relay certificates,
          tls-crypt key, password + scrypt hash of every robot (durable: every PKI file fsynced)
  render  cloud-init user-data, clone secrets and edge bundle of every robot, in memory
  write   both bundles of every robot written to disk (reported, outside the target)
Targets: init + issue + render under 2 s for 100 robots (issue #2); under 10 s for 1,000 robots
and at most 12x the time of 100 (issue #12: no cost may grow faster than the fleet).
The lab inventory's pools hold 245 clones: larger fleets get vpn.pool 10.64.0.0/10 and
common.cidr 10.200.0.0/16.

Run: .venv/bin/python bench/render_fleet.py [--robots 100,1000] [--repeat 3] [--profile]
Writes bench/results/render_fleet.json (top-level robots/runs/median_s/meets_target: the first size).
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as dt
import json
import os
import platform
import pstats
import statistics
import tempfile
import time
from pathlib import Path

import yaml

from ccrp_cli.ops import vpn
from ccrp_cli.models.addressing import capacity
from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.models.inventory import Inventory
from ccrp_cli.render import bundles, cloudinit
from ccrp_cli.services.registry import boots

ROOT = Path(__file__).resolve().parent.parent
TARGET_S = 2.0  # 100 robots
TARGET_LARGE_S = 10.0  # 1,000 robots
TARGET_RATIO = 12.0  # largest size / smallest size
WIDE_POOLS = {"vpn": {"pool": "10.64.0.0/10"}, "common": {"cidr": "10.200.0.0/16"}}


def inventory(robots: int) -> dict:
    inv = yaml.safe_load((ROOT / "inventories" / "lab.yaml").read_text())
    inv.update(fleet="bench", robots=[{"name": f"bot{i}"} for i in range(1, robots + 1)])
    inv.pop("template", None)
    if robots > capacity(Inventory.model_validate(inv)):
        for section, values in WIDE_POOLS.items():
            inv[section].update(values)
    return inv


def run_once(robots: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="ccrp-bench-") as tmp:
        tmp_path = Path(tmp)
        (tmp_path / "fleet.yaml").write_text(yaml.safe_dump(inventory(robots)))
        os.environ["CCRP_HOME"] = str(tmp_path / "home")
        t = {}
        t0 = time.perf_counter()
        fleet = Fleet.open(tmp_path / "fleet.yaml")
        vpn.init(fleet)
        t1 = time.perf_counter()
        names = [r.name for r in fleet.inventory.robots]
        state = fleet.store.load_state()
        plan = fleet.plan(state)
        fleet.pki.issue_fleet({n: str(plan[n].common_ip) for n in names}, fleet.inventory.vpn.cert_days)  # as fleet up
        t2 = time.perf_counter()
        rendered = []
        for name in names:
            view = clone_view(fleet, state, name)
            creds = fleet.pki.credentials(name)
            cloudinit.user_data(view, boots())
            rendered.append((name, bundles.clone_secrets(view, creds), bundles.edge_bundle(view, creds, "203.0.113.10")))
        t3 = time.perf_counter()
        for name, secret_files, edge_files in rendered:
            bundles.write_bundle(tmp_path / "out" / name / "secrets", secret_files, {"robot": name})
            bundles.write_bundle(tmp_path / "out" / name / "edge", edge_files, {"robot": name})
        t4 = time.perf_counter()
        t.update(init=t1 - t0, issue=t2 - t1, render=t3 - t2, write=t4 - t3, target_total=t3 - t0)
        return t


def summary(robots: int, runs: list[dict[str, float]], target: float) -> dict:
    median = {k: round(statistics.median(r[k] for r in runs), 3) for k in runs[0]}
    return {
        "robots": robots,
        "runs": [{k: round(v, 3) for k, v in r.items()} for r in runs],
        "median_s": median,
        "target_s": target,
        "meets_target": median["target_total"] < target,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="100,1000", help="fleet sizes, comma-separated (smallest first)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", action="store_true", help="print the top functions of one more run of the largest size")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "render_fleet.json")
    args = ap.parse_args()
    sizes = sorted({int(n) for n in args.robots.split(",")})
    runs: dict[int, list] = {n: [] for n in sizes}
    for _ in range(args.repeat):
        for n in sizes:
            runs[n].append(run_once(n))
    per_size = [summary(n, runs[n], TARGET_S if n <= 100 else TARGET_LARGE_S) for n in sizes]
    result = {
        "benchmark": "render_fleet",
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
        **per_size[0],
        "sizes": per_size,
    }
    for s in per_size:
        m = s["median_s"]
        print(f"{s['robots']} robots, median of {args.repeat}: init {m['init']:.2f}s, issue {m['issue']:.2f}s, "
              f"render {m['render']:.2f}s -> {m['target_total']:.2f}s (target < {s['target_s']}s: "
              f"{'met' if s['meets_target'] else 'MISSED'}); writing bundles {m['write']:.2f}s")
    if len(sizes) > 1:
        small, large = per_size[0], per_size[-1]
        ratio = large["median_s"]["target_total"] / small["median_s"]["target_total"]
        # Per repetition too: both sizes ran back to back, under the same load.
        paired = [b["target_total"] / a["target_total"] for a, b in zip(small["runs"], large["runs"])]
        result["scaling"] = {
            "sizes": [small["robots"], large["robots"]],
            "ratio": round(ratio, 2),
            "ratio_per_repeat": [round(r, 2) for r in paired],
            "fleet_ratio": large["robots"] / small["robots"],
            "target_ratio": TARGET_RATIO,
            "meets_target": ratio <= TARGET_RATIO,
        }
        print(f"{large['robots']} / {small['robots']} robots: {ratio:.1f}x (per repetition "
              f"{', '.join(f'{r:.1f}' for r in paired)}; target <= {TARGET_RATIO:g}x: "
              f"{'met' if ratio <= TARGET_RATIO else 'MISSED'})")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    if args.profile:
        prof = cProfile.Profile()
        prof.runcall(run_once, sizes[-1])
        pstats.Stats(prof).sort_stats("cumulative").print_stats(25)


if __name__ == "__main__":
    main()
