"""Everyday commands on a 20-clone Docker fleet, timed through the CLI (issue 12).

  status   `ccrp status --json` of the whole fleet (target: under 3 s)
  up       a second `ccrp fleet up` that has nothing to do (target: under 5 s)

Medians over --rounds, each a subprocess running the real CLI. --profile also runs each command
once under cProfile and writes the top functions (cumulative) to bench/results/fleet_ops.<cmd>.txt.
The fleet is one of its own (`ops<random>`, free subnets, a temp CCRP_HOME, see crash_scale.py);
`ccrp fleet down` and a sweep of everything labelled with it run at the end, even on failure.

Run: .venv/bin/python bench/fleet_ops.py [--clones 20] [--rounds 5] [--profile]
Writes bench/results/fleet_ops.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import pstats
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from crash_scale import RESULTS, ROOT, CrashFleet, _interrupted  # noqa: E402

TARGETS_S = {"status": 3.0, "up": 5.0}


def timed(fleet: CrashFleet, *args: str) -> tuple[float, object]:
    t0 = time.perf_counter()
    proc = fleet.check_call(*args)
    return time.perf_counter() - t0, json.loads(proc.stdout)


def profiled(fleet: CrashFleet, name: str, *args: str) -> str:
    """One run of `ccrp ARGS` under cProfile; the top of its cumulative listing."""
    out = RESULTS / f"fleet_ops.{name}.prof"
    argv = [sys.executable, "-m", "cProfile", "-o", str(out), "-m", "ccrp_cli", *args, "-i", str(fleet.inventory)]
    subprocess.run(argv, cwd=ROOT, env=fleet.env(), capture_output=True, text=True, timeout=600, check=True)
    text = RESULTS / f"fleet_ops.{name}.txt"
    with text.open("w") as fh:
        pstats.Stats(str(out), stream=fh).sort_stats("cumulative").print_stats(40)
    out.unlink()
    return str(text.relative_to(ROOT))


def serving(rows: list[dict]) -> int:
    """Clones status shows running with their master answering (recorded: under load a health
    probe can time out, which is a result too)."""
    return sum(r["status"] == "running" and r["master_reachable"] for r in rows)


def run(clones: int, rounds: int, profile: bool, progress) -> dict:
    fleet = CrashFleet.create(prefix="ops")
    result: dict = {"benchmark": "fleet_ops", "fleet": fleet.name, "clones": clones, "rounds": rounds}
    previous = signal.signal(signal.SIGTERM, _interrupted)
    try:
        t0 = time.monotonic()
        fleet.prepare()
        progress(f"{fleet.name}: CA and snapshot in {time.monotonic() - t0:.0f} s")
        wall, rows = timed(fleet, "fleet", "scale", str(clones), "--json")
        if sum(r["action"] == "created" for r in rows) != clones:
            raise RuntimeError(f"fleet scale {clones}: {rows}")
        result["scale_s"] = round(wall, 2)
        progress(f"fleet scale {clones}: {wall:.1f} s")
        samples: dict[str, list[float]] = {"status": [], "up": []}
        for r in range(rounds):
            wall, rows = timed(fleet, "status", "--json")
            result.setdefault("status_serving", []).append(serving(rows))
            samples["status"].append(round(wall, 2))
            wall, rows = timed(fleet, "fleet", "up", "--json")
            if any(row["action"] != "reused" for row in rows):
                raise RuntimeError(f"a second fleet up changed something: {rows}")
            samples["up"].append(round(wall, 2))
            progress(f"round {r + 1}: status {samples['status'][-1]:.2f} s, fleet up (no-op) {samples['up'][-1]:.2f} s")
        for name, samples_ in samples.items():
            median = round(statistics.median(samples_), 2)
            result[name] = {"median_s": median, "samples": samples_, "target_s": TARGETS_S[name],
                            "meets_target": median < TARGETS_S[name]}
        if profile:
            result["profiles"] = {"status": profiled(fleet, "status", "status", "--json"),
                                  "up": profiled(fleet, "up", "fleet", "up", "--json")}
    finally:
        left = fleet.cleanup()
        signal.signal(signal.SIGTERM, previous)
        result["left_after_cleanup"] = left
        if left:
            progress(f"cleanup left: {left}")
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clones", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--out", type=Path, default=RESULTS / "fleet_ops.json")
    args = ap.parse_args()
    progress = lambda msg: print(f"bench: {msg}", file=sys.stderr, flush=True)  # noqa: E731
    result = run(args.clones, args.rounds, args.profile, progress)
    result["date"] = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    result["machine"] = {"cpus": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for name in ("status", "up"):
        r = result[name]
        print(f"{name}: median {r['median_s']:.2f} s of {r['samples']} (target < {r['target_s']:g} s: "
              f"{'met' if r['meets_target'] else 'MISSED'})")


if __name__ == "__main__":
    main()
