"""Crash safety of `ccrp fleet scale` on Docker: kill -9 at a random moment, then converge (issue 11).

Every trial picks a size K in 1..--max-size other than the fleet's current one (so trials go up
and down), starts `ccrp fleet scale K` as a subprocess, SIGKILLs it after a random delay, and
then checks what the kill left and what the next run makes of it:

  left     state.json still parses (FleetStore.load_state); which clone containers exist, and
           any `.state.json.*.tmp` a write cut short left behind
  rerun    `ccrp fleet scale K --json` runs to completion (exit 0, no robot failed) without
           waiting for a lock (the killed run's flock died with it): its wall time is the
           convergence time
  check    K robots in state, each with exactly one clone container (no duplicate), running,
           phase `ready`, master answering in `ccrp status --json`; no container or secrets
           volume carrying the fleet's labels for a robot state does not know (no orphan); no
           temp file of a cut-short state write left in the store

The bench works on a fleet of its own (`crash<random>`, free subnets, a temp CCRP_HOME); at the
end, even on failure or Ctrl-C, it runs `ccrp fleet down` and removes every container, volume,
network and image labelled with that fleet (and nothing else).

Run: .venv/bin/python bench/crash_scale.py [--trials 20] [--max-size 4] [--max-delay 6] [--seed N]
Writes bench/results/crash_scale.json (--out to change). tests/e2e/test_crash_safety.py runs 3
trials of the same code.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import random
import secrets
import signal
import statistics
import sys
import time
from pathlib import Path


ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
sys.path.insert(0, str(ROOT))  # the fleet and its trial are the crash-safety test's (tests/e2e/crash.py)

from tests.e2e.crash import CrashFleet  # noqa: E402


def plan_trials(trials: int, aimed: int, max_size: int, max_delay: float, rng: random.Random, start: int):
    """(from, size, delay, aimed) per trial. Random trials: each size differs from the one before,
    so they scale up and down. Aimed trials, spread among them, always grow the fleet (at the
    largest size one waits for the next trial; if none is left, one more random trial goes first)."""
    current, random_left, aimed_left = start, trials, aimed
    while random_left or aimed_left:
        if aimed_left and current < max_size and random_left * aimed <= aimed_left * trials:
            size = rng.randint(current + 1, max_size)
            aimed_left -= 1
            yield current, size, 0.0, True
        else:
            size = rng.choice([k for k in range(1, max_size + 1) if k != current])
            random_left = max(0, random_left - 1)
            # Removing clones takes a second or two, adding one several: aim the kill inside the run.
            yield current, size, rng.uniform(0.3, max_delay if size > current else max_delay / 2), False
        current = size


def run(trials: int, aimed: int, max_size: int, max_delay: float, seed: int, progress=print) -> dict:
    rng = random.Random(seed)
    fleet = CrashFleet.create()
    result: dict = {"fleet": fleet.name, "seed": seed, "trials": [], "host": {
        "machine": platform.machine(), "cpus": os.cpu_count(), "python": platform.python_version()}}
    previous = signal.signal(signal.SIGTERM, _interrupted)  # `kill` cleans up as Ctrl-C does
    try:
        t0 = time.monotonic()
        fleet.prepare()
        result["prepare_s"] = round(time.monotonic() - t0, 1)
        start = 2
        t0 = time.monotonic()
        fleet.check_call("fleet", "scale", str(start))
        result["baseline_scale_s"] = round(time.monotonic() - t0, 2)
        progress(f"{fleet.name}: snapshot in {result['prepare_s']} s, scale {start} in {result['baseline_scale_s']} s")
        for i, (frm, size, delay, aim) in enumerate(plan_trials(trials, aimed, max_size, max_delay, rng, start), 1):
            try:
                t = fleet.trial(i, size, frm, delay, aim)
            except Exception as exc:  # noqa: BLE001 - the bench's own failure is a result too; go on
                t = {"trial": i, "aimed": aim, "from_size": frm, "to_size": size, "kill_delay_s": round(delay, 2),
                     "left": {"killed": None, "state_parses": None, "clones": {}, "temp_files": []},
                     "rerun": {"exit": None, "convergence_s": None, "waited_for_lock": False, "failed": {},
                               "problems": [f"bench error: {type(exc).__name__}: {exc}"]}, "ok": False}
            result["trials"].append(t)
            progress(describe(t))
    finally:
        left = fleet.cleanup()
        signal.signal(signal.SIGTERM, previous)
        result["left_after_cleanup"] = left
        result["log"] = fleet.log
        if left:
            progress(f"cleanup left: {left}")
    result["summary"] = summary(result["trials"])
    return result


def _interrupted(*_) -> None:
    raise KeyboardInterrupt


def describe(t: dict) -> str:
    left, rerun = t["left"], t["rerun"]
    killed = "killed" if left["killed"] else "had already ended"
    found = "ok" if t["ok"] else "FAIL: " + "; ".join(rerun["problems"] + list(rerun["failed"].values()))[:600]
    aim = " (aimed: secrets pushed)" if t["aimed"] else ""
    return (f"trial {t['trial']:2}: scale {t['from_size']}->{t['to_size']} {killed} at {t['kill_delay_s']:.2f}s{aim}, "
            f"left {sum(map(len, left['clones'].values()))} clones, state "
            f"{'parses' if left['state_parses'] else 'BROKEN'}; rerun exit {rerun['exit']} in "
            f"{rerun['convergence_s']}s: {found}")


def summary(trials: list[dict]) -> dict:
    killed = [t for t in trials if t["left"]["killed"]]
    conv = [t["rerun"]["convergence_s"] for t in trials if t["rerun"]["convergence_s"] is not None]
    return {
        "trials": len(trials),
        "aimed": sum(t["aimed"] for t in trials),
        "aimed_ok": sum(t["ok"] for t in trials if t["aimed"]),
        "killed_mid_run": len(killed),
        "finished_before_kill": len(trials) - len(killed),
        "ok": sum(t["ok"] for t in trials),
        "state_parsed_after_kill": sum(bool(t["left"]["state_parses"]) for t in trials),
        "clones_left_by_kill": sum(sum(map(len, t["left"]["clones"].values())) for t in killed),
        "temp_files_left_by_kill": sum(len(t["left"]["temp_files"]) for t in killed),
        "duplicates": sum(len(t["rerun"].get("duplicates", {})) for t in trials),
        "orphans": sum(len(t["rerun"].get("orphans", [])) + len(t["rerun"].get("orphan_volumes", [])) for t in trials),
        "rerun_waited_for_lock": sum(t["rerun"]["waited_for_lock"] for t in trials),
        "kill_delay_s": {"min": min((t["kill_delay_s"] for t in trials), default=None),
                         "max": max((t["kill_delay_s"] for t in trials), default=None)},
        "convergence_s": {"median": round(statistics.median(conv), 2) if conv else None,
                          "min": min(conv, default=None), "max": max(conv, default=None)},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=20, help="kills at random moments")
    ap.add_argument("--aimed", type=int, default=5, help="more kills, each as a new clone's secrets land")
    ap.add_argument("--max-size", type=int, default=4, help="sizes go between 1 and this")
    ap.add_argument("--max-delay", type=float, default=6.0, help="kill delays are uniform in [0.3, this] s (half of it when scaling down)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--out", type=Path, default=RESULTS / "crash_scale.json")
    args = ap.parse_args()
    seed = args.seed if args.seed is not None else secrets.randbelow(2**31)
    started = dt.datetime.now(dt.timezone.utc)
    try:
        result = run(args.trials, args.aimed, args.max_size, args.max_delay, seed)
    except KeyboardInterrupt:
        raise SystemExit("interrupted; the bench fleet was removed")
    result["date"] = started.strftime("%Y-%m-%d %H:%M UTC")
    result["command"] = " ".join(["bench/crash_scale.py", *sys.argv[1:]])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["summary"], indent=2))
    if result["summary"]["ok"] != result["summary"]["trials"]:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
