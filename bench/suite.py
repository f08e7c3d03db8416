"""Where the test suite's time goes, from pytest's JUnit XML: the time of each work unit (a module
that shares a fleet, a scenario backend, the unit tests), the slowest tests, and, for a parallel
run, how busy each worker was against the run's wall time.

Run: .venv/bin/python -m pytest -n 3 --dist loadgroup --no-loadscope-reorder --junitxml=/tmp/suite.xml
     .venv/bin/python bench/suite.py /tmp/suite.xml --wall SECONDS [--label after] [--out bench/results/suite.json]
(--wall: the run's own figure, `in NNNN.NNs` on pytest's last line.) Several files compare side by side.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import xml.etree.ElementTree as ET
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def unit_of(classname: str, name: str) -> str:
    """The work unit a test belongs to (tests/conftest.py _group): its module, a scenario backend, or "unit"."""
    module = classname.replace(".", "/") + ".py"
    if module.startswith("tests/unit/"):
        return "tests/unit (each test on its own)"
    backend = re.search(r"\[(docker|openstack|gcp|aws)[\]-]", name)
    if module.endswith("test_user_path.py") and backend:
        return f"{module}/{backend.group(1)}"
    return module


def summarize(path: Path, wall: float | None, label: str) -> dict:
    root = ET.parse(path).getroot()
    units: dict[str, float] = collections.Counter()
    tests, outcomes = [], collections.Counter()
    for case in root.iter("testcase"):
        seconds = float(case.get("time") or 0)
        name = case.get("name", "").split("@")[0]  # xdist's work unit suffix
        units[unit_of(case.get("classname", ""), name)] += seconds
        tests.append((seconds, f"{case.get('classname')}::{name}"))
        kind = next((c.tag for c in case if c.tag in ("failure", "error", "skipped")), "passed")
        outcomes[kind] += 1
    busy = sum(units.values())
    out = {"label": label, "junit": str(path), "tests": len(tests), "outcomes": dict(outcomes),
           "test_seconds": round(busy, 1), "wall_seconds": wall,
           "units": {k: round(v, 1) for k, v in sorted(units.items(), key=lambda kv: -kv[1])},
           "slowest": [{"seconds": round(s, 1), "test": t} for s, t in sorted(tests, reverse=True)[:25]]}
    if wall:
        out["parallelism"] = round(busy / wall, 2)  # tests' seconds per second of the run
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("junit", nargs="+", type=Path)
    parser.add_argument("--wall", type=float, nargs="*", default=[], help="each run's wall time, in order")
    parser.add_argument("--label", nargs="*", default=[], help="each run's label, in order")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "suite.json")
    args = parser.parse_args()
    runs = [summarize(p, args.wall[i] if i < len(args.wall) else None, args.label[i] if i < len(args.label) else p.stem)
            for i, p in enumerate(args.junit)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(runs, indent=1) + "\n")
    for run in runs:
        wall = f", wall {run['wall_seconds']:.0f} s, parallelism {run['parallelism']}" if run["wall_seconds"] else ""
        print(f"{run['label']}: {run['tests']} tests {run['outcomes']}, tests' time {run['test_seconds']:.0f} s{wall}")
        for unit, seconds in list(run["units"].items())[:12]:
            print(f"  {seconds:8.1f} s  {unit}")
    print(f"-> {args.out}")


if __name__ == "__main__":
    main()
