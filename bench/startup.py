"""Start-up cost of the `ccrp` CLI compared with importing openstacksdk (docs/architecture.md: start-up cost).

Measures, interleaved round by round so machine noise hits every command alike:
  ccrp_help        `ccrp --help` (the venv's console script)
  import_openstack `python -c "import openstack"` (needs `.venv/bin/pip install openstacksdk`)
  import_cli       `python -c "import ccrp_cli.cli.main"`
then checks with `python -X importtime` that importing the CLI pulls in no cloud SDK.

And the CPU time (user + system, from the child's rusage) of commands that do work on the local
default, whose cost every `ccrp` call in a script or a test pays: `fleet validate`, `fleet plan`
and `status` of inventories/lab.yaml (no clone needs to exist; plan and status ask the Docker
engine). `--baseline PATH` runs those on another checkout of ccrp too (PYTHONPATH), in the same
rounds, so a change is compared with the code before it in one run.

Run: .venv/bin/python bench/startup.py [--rounds 15] [--warmup 2] [--baseline /path/to/old/checkout]
Writes bench/results/startup.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import statistics
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
VENV_BIN = ROOT / ".venv" / "bin"
PYTHON = str(VENV_BIN / "python")
RESULTS = ROOT / "bench" / "results"

COMMANDS: dict[str, list[str]] = {
    "python_baseline": [PYTHON, "-c", "pass"],  # reference: the interpreter's own start-up floor
    "ccrp_help": [str(VENV_BIN / "ccrp"), "--help"],
    "import_openstack": [PYTHON, "-c", "import openstack"],
    "import_cli": [PYTHON, "-c", "import ccrp_cli.cli.main"],
}
# Commands that do work: their CPU time is what a script pays per call (the engine must run).
WORK: dict[str, list[str]] = {
    "fleet_validate": [PYTHON, "-m", "ccrp_cli", "fleet", "validate", "--json", "-i", "inventories/lab.yaml"],
    "fleet_plan": [PYTHON, "-m", "ccrp_cli", "fleet", "plan", "--json", "-i", "inventories/lab.yaml"],
    "status": [PYTHON, "-m", "ccrp_cli", "status", "--json", "-i", "inventories/lab.yaml"],
}
# Must never be imported by `import ccrp_cli.cli.main` (docs/architecture.md: start-up cost).
FORBIDDEN = ("openstack", "google.cloud", "boto3", "botocore", "docker", "paramiko")
TARGET_RATIO = 0.5


def _env() -> dict[str, str]:
    env = dict(os.environ)
    for var in ("PYTHONSTARTUP", "PYTHONPROFILEIMPORTTIME", "PYTHONDONTWRITEBYTECODE", "PYTHONVERBOSE"):
        env.pop(var, None)
    env["COLUMNS"] = "100"  # rich/typer help layout independent of the caller's terminal
    return env


def time_once(argv: list[str], env: dict[str, str], cwd: Path = ROOT) -> tuple[float, float]:
    """(wall, CPU) seconds of one run; CPU is user + system of the child, from rusage."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(argv, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    elapsed = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"startup bench: {' '.join(argv)} failed ({proc.returncode}): {proc.stderr.decode()[-500:]}")
    return elapsed, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def percentile(values: list[float], q: float) -> float:
    """Linear-interpolation percentile (q in 0..100)."""
    xs = sorted(values)
    pos = (len(xs) - 1) * q / 100
    lo = int(pos)
    hi = min(lo + 1, len(xs) - 1)
    return xs[lo] + (xs[hi] - xs[lo]) * (pos - lo)


def summary(values: list[float]) -> dict[str, float]:
    return {
        "median_s": statistics.median(values),
        "p90_s": percentile(values, 90),
        "min_s": min(values),
        "max_s": max(values),
        "mean_s": statistics.fmean(values),
    }


def importtime(env: dict[str, str]) -> dict[str, object]:
    """Parse `python -X importtime -c "import ccrp_cli.cli.main"` (microseconds on stderr)."""
    proc = subprocess.run(
        [PYTHON, "-X", "importtime", "-c", "import ccrp_cli.cli.main"],
        cwd=ROOT, env=env, capture_output=True, text=True, check=True,
    )
    rows = []
    for line in proc.stderr.splitlines():
        if not line.startswith("import time:") or "self [us]" in line:
            continue
        self_us, cum_us, name = line.removeprefix("import time:").split("|", 2)
        depth = (len(name) - len(name.lstrip())) // 2  # importtime indents nested imports by 2
        rows.append({"module": name.strip(), "self_us": int(self_us), "cumulative_us": int(cum_us), "depth": depth})
    modules = {r["module"] for r in rows}
    # Cross-check with sys.modules (importtime lists only modules imported for the first time).
    probe = subprocess.run(
        [PYTHON, "-c", "import json, sys, ccrp_cli.cli.main; print(json.dumps(sorted(sys.modules)))"],
        cwd=ROOT, env=env, capture_output=True, text=True, check=True,
    )
    modules |= set(json.loads(probe.stdout))
    hits = sorted(m for m in modules if any(m == f or m.startswith(f + ".") for f in FORBIDDEN))
    top = sorted(rows, key=lambda r: r["cumulative_us"], reverse=True)[:5]
    # Cost per top-level package: cumulative time of the rows where a package is entered from
    # another one (importtime prints children before their parent, so walk it backwards).
    by_package: dict[str, int] = {}
    stack: list[tuple[int, str]] = []
    for r in reversed(rows):
        root = r["module"].split(".")[0]
        while stack and stack[-1][0] >= r["depth"]:
            stack.pop()
        if not stack or stack[-1][1] != root:
            by_package[root] = by_package.get(root, 0) + r["cumulative_us"]
        stack.append((r["depth"], root))
    packages = sorted(by_package.items(), key=lambda kv: kv[1], reverse=True)[:10]
    return {
        "modules_imported": len(modules),
        "forbidden_checked": list(FORBIDDEN),
        "forbidden_imported": hits,
        "top5_cumulative": top,
        "top10_packages_us": dict(packages),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS / "startup.json")
    ap.add_argument("--baseline", type=Path, help="another checkout of ccrp whose working commands run alongside")
    args = ap.parse_args()

    env = _env()
    for name, argv in COMMANDS.items():
        if not Path(argv[0]).exists():
            sys.exit(f"startup bench: {argv[0]} not found ({name})")
    # name -> (argv, env, cwd): the start-up commands, then the working ones on this tree (and the
    # baseline's; run in the tree, as `python -m` puts the working directory first on the path).
    runs = {n: (argv, env, ROOT) for n, argv in COMMANDS.items()}
    home = tempfile.mkdtemp(prefix="ccrp-startup-")  # no fleet of the user's is read or written
    trees = {"": ROOT, **({"baseline_": args.baseline.resolve()} if args.baseline else {})}
    # `status` reads the fleet's PKI: made once, as a user's `ccrp vpn init`.
    subprocess.run([PYTHON, "-m", "ccrp_cli", "vpn", "init", "-i", "inventories/lab.yaml"], cwd=ROOT, check=True,
                   env={**env, "CCRP_HOME": home}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    for prefix, tree in trees.items():
        for n, argv in WORK.items():
            runs[f"{prefix}{n}"] = (argv, {**env, "PYTHONPATH": str(tree), "CCRP_HOME": home}, tree)

    names = list(runs)
    times: dict[str, list[float]] = {n: [] for n in names}
    cpu: dict[str, list[float]] = {n: [] for n in names}
    for r in range(args.warmup + args.rounds):
        # Rotate the order every round so no command always runs first (cold) or last.
        k = r % len(names)
        for name in names[k:] + names[:k]:
            wall, used = time_once(*runs[name])
            if r >= args.warmup:
                times[name].append(wall)
                cpu[name].append(used)

    shutil.rmtree(home, ignore_errors=True)
    stats = {n: summary(v) for n, v in times.items()}
    cpu_median = {n: statistics.median(v) for n, v in cpu.items()}
    compared = {n: cpu_median[n] / cpu_median[f"baseline_{n}"] for n in WORK if f"baseline_{n}" in cpu_median}
    ratio = stats["ccrp_help"]["median_s"] / stats["import_openstack"]["median_s"]
    imports = importtime(env)

    result = {
        "benchmark": "startup",
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "python": platform.python_version(),
            "implementation": platform.python_implementation(),
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
        },
        "rounds": args.rounds,
        "warmup_rounds": args.warmup,
        "commands": {n: " ".join(Path(a).name if i == 0 else a for i, a in enumerate(argv))
                     for n, argv in {**COMMANDS, **WORK}.items()},
        "baseline_tree": str(args.baseline) if args.baseline else None,
        "stats": stats,
        "cpu_median_s": cpu_median,
        "cpu_ratio_over_baseline": compared,
        "samples_s": times,
        "ratio_ccrp_help_over_import_openstack": ratio,
        "ratio_target": TARGET_RATIO,
        "ratio_ok": ratio <= TARGET_RATIO,
        "importtime": imports,
        "no_forbidden_imports_ok": not imports["forbidden_imported"],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")

    print(f"startup: {args.rounds} rounds (+{args.warmup} warm-up), python {platform.python_version()}, {os.cpu_count()} cpus")
    print(f"  {'command':<18}{'median':>9}{'p90':>9}{'min':>9}")
    for n, s in stats.items():
        print(f"  {n:<18}{s['median_s'] * 1000:>7.0f}ms{s['p90_s'] * 1000:>7.0f}ms{s['min_s'] * 1000:>7.0f}ms")
    print("  CPU per call (user + system, median): " + ", ".join(f"{n} {v * 1000:.0f} ms" for n, v in cpu_median.items()))
    for n, ratio_n in compared.items():
        print(f"  {n}: {ratio_n:.2f}x the baseline's CPU")
    print(f"  ratio median(ccrp --help)/median(import openstack) = {ratio:.2f} (target <= {TARGET_RATIO}): "
          f"{'OK' if ratio <= TARGET_RATIO else 'MISSED'}")
    bad = imports["forbidden_imported"]
    print(f"  cloud SDK modules imported by ccrp_cli.cli.main: {', '.join(bad) if bad else 'none'}")
    print("  top 5 cumulative import costs (import ccrp_cli.cli.main):")
    for row in imports["top5_cumulative"]:
        print(f"    {row['cumulative_us'] / 1000:7.1f} ms  {row['module']}")
    print("  by package (inclusive, entered from another package): " + ", ".join(
        f"{k} {v / 1000:.0f} ms" for k, v in list(imports["top10_packages_us"].items())[:6]))
    print(f"  -> {args.out.relative_to(ROOT) if args.out.is_relative_to(ROOT) else args.out}")


if __name__ == "__main__":
    main()
