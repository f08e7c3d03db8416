"""Issue certificates and render everything for a 100-robot fleet, in one process.

Phases (fresh CCRP_HOME per repetition, median of --repeat runs):
  init    Fleet.open of a 100-robot inventory + vpn.init (CA, CRL, address slots)
  issue   vpn.issue for every robot: client + server cert, tls-crypt key, password + scrypt hash
          (durable: every PKI file is fsynced)
  render  cloud-init user-data, clone secrets and edge bundle of every robot, in memory
  write   both bundles of every robot written to disk (reported, outside the target)
Target (issue #2): init + issue + render under 2 s on this machine.

Run: .venv/bin/python bench/render_fleet.py [--robots 100] [--repeat 3] [--profile]
Writes bench/results/render_fleet.json.
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

from ccrp_cli import vpn
from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.render import bundles, cloudinit

ROOT = Path(__file__).resolve().parent.parent
TARGET_S = 2.0


def run_once(robots: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="ccrp-bench-") as tmp:
        tmp_path = Path(tmp)
        inv = yaml.safe_load((ROOT / "inventories" / "lab.yaml").read_text())
        inv.update(fleet="bench", robots=[{"name": f"bot{i}"} for i in range(1, robots + 1)])
        inv.pop("template", None)
        (tmp_path / "fleet.yaml").write_text(yaml.safe_dump(inv))
        os.environ["CCRP_HOME"] = str(tmp_path / "home")
        t = {}
        t0 = time.perf_counter()
        fleet = Fleet.open(tmp_path / "fleet.yaml")
        vpn.init(fleet)
        t1 = time.perf_counter()
        names = [r.name for r in fleet.inventory.robots]
        for name in names:
            vpn.issue(fleet, name)
        t2 = time.perf_counter()
        state = fleet.store.load_state()
        rendered = []
        for name in names:
            view = clone_view(fleet, state, name)
            creds = fleet.pki.credentials(name)
            cloudinit.user_data(view)
            rendered.append((name, bundles.clone_secrets(view, creds), bundles.edge_bundle(view, creds, "203.0.113.10")))
        t3 = time.perf_counter()
        for name, secret_files, edge_files in rendered:
            bundles.write_bundle(tmp_path / "out" / name / "secrets", secret_files, {"robot": name})
            bundles.write_bundle(tmp_path / "out" / name / "edge", edge_files, {"robot": name})
        t4 = time.perf_counter()
        t.update(init=t1 - t0, issue=t2 - t1, render=t3 - t2, write=t4 - t3, target_total=t3 - t0)
        return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", action="store_true", help="print the top functions of one more run")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "render_fleet.json")
    args = ap.parse_args()
    runs = [run_once(args.robots) for _ in range(args.repeat)]
    median = {k: round(statistics.median(r[k] for r in runs), 3) for k in runs[0]}
    result = {
        "benchmark": "render_fleet",
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()},
        "robots": args.robots,
        "runs": [{k: round(v, 3) for k, v in r.items()} for r in runs],
        "median_s": median,
        "target_s": TARGET_S,
        "meets_target": median["target_total"] < TARGET_S,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"{args.robots} robots, median of {args.repeat}: init {median['init']:.2f}s, issue {median['issue']:.2f}s, "
          f"render {median['render']:.2f}s -> {median['target_total']:.2f}s (target < {TARGET_S}s: "
          f"{'met' if result['meets_target'] else 'MISSED'}); writing bundles {median['write']:.2f}s")
    if args.profile:
        prof = cProfile.Profile()
        prof.runcall(run_once, args.robots)
        pstats.Stats(prof).sort_stats("cumulative").print_stats(20)


if __name__ == "__main__":
    main()
