"""Everything ccrp computes and writes for a 100-robot fleet before any cloud call, in one process.

Per repetition (fresh temp dirs, fresh CCRP_HOME):
  init        Fleet.open (inventory of N robots, docker provider) + vpn.init (CA, CRL, state)
  issue       vpn.issue for every robot: client + server cert (ECDSA P-256 by default),
              tls-crypt key, VPN password + scrypt hash
  cloud_init  render.cloudinit.user_data(fleet.clone_view(...)) for every robot
  bundles     render.bundles.clone_secrets + edge_bundle (remote 203.0.113.10) for every robot,
              each written with bundles.write_bundle
The inventory is generated from inventories/lab.yaml's shape: robots bot1..botN, no sharing imports.
If the median total misses the target (or with --profile), one more repetition runs under cProfile
and the time is attributed to the suspects (scrypt, index.json load/save, fsync, key generation...);
then one instrumented run (timers around the suspects, no profiler overhead) and "what-if" runs
with fsync and/or scrypt stubbed out IN THIS PROCESS ONLY (diagnosis; ccrp_cli is not modified).

Run: .venv/bin/python bench/render_fleet.py [--robots 100] [--repeat 3] [--profile] [--tmp DIR]
Writes bench/results/render_fleet.json.
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import datetime as dt
import io
import json
import os
import platform
import pstats
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
LAB = ROOT / "inventories" / "lab.yaml"
REMOTE = "203.0.113.10"
TARGET_S = 2.0
PHASES = ("init", "issue", "cloud_init", "bundles")

# Imported up front: import cost belongs to bench/startup.py, not to this benchmark.
from ccrp_cli import vpn  # noqa: E402
from ccrp_cli.fleet import Fleet, clone_view  # noqa: E402
from ccrp_cli.render import bundles, cloudinit  # noqa: E402
from ccrp_cli.pki import secrets as pki_secrets  # noqa: E402
from ccrp_cli.pki import store as pki_store  # noqa: E402
from ccrp_cli import fleet as fleet_mod, store as fleet_store  # noqa: E402


def write_inventory(path: Path, robots: int, key_type: str | None) -> None:
    inv = yaml.safe_load(LAB.read_text())
    inv["fleet"] = "bench"
    inv["robots"] = [{"name": f"bot{i}", "type": "generic"} for i in range(1, robots + 1)]
    inv.pop("template", None)
    if key_type:
        inv["vpn"]["key_type"] = key_type
    path.write_text(yaml.safe_dump(inv, sort_keys=False))


def _clone_view(fleet: Fleet, state: object, name: str) -> object:
    return clone_view(fleet, state, name)  # a module-level hop so the instrumented run can wrap it


def run_once(robots: int, key_type: str | None, tmp_base: str | None) -> dict[str, object]:
    with tempfile.TemporaryDirectory(prefix="ccrp-bench-", dir=tmp_base) as tmp:
        tmp_path = Path(tmp)
        inventory = tmp_path / "fleet.yaml"
        write_inventory(inventory, robots, key_type)
        os.environ["CCRP_HOME"] = str(tmp_path / "home")
        out = tmp_path / "out"
        t: dict[str, float] = {}

        t0 = time.perf_counter()
        fleet = Fleet.open(inventory)
        t_open = time.perf_counter()
        vpn.init(fleet)
        t1 = time.perf_counter()
        t["init"] = t1 - t0

        names = [r.name for r in fleet.inventory.robots]
        for name in names:
            vpn.issue(fleet, name)
        t2 = time.perf_counter()
        t["issue"] = t2 - t1

        state = fleet.store.load_state()
        ud_bytes = 0
        for name in names:
            ud_bytes += len(cloudinit.user_data(_clone_view(fleet, state, name)).encode())
        t3 = time.perf_counter()
        t["cloud_init"] = t3 - t2

        files = 0
        for name in names:
            view = _clone_view(fleet, state, name)
            creds = fleet.pki.credentials(name)  # read once, used by both bundles
            secret_files = bundles.clone_secrets(view, creds)
            bundles.write_bundle(out / name / "clone-secrets", secret_files,
                                 {"fleet": fleet.name, "robot": name, "kind": "clone-secrets"})
            edge_files = bundles.edge_bundle(view, creds, REMOTE)
            bundles.write_bundle(out / name / "edge", edge_files,
                                 {"fleet": fleet.name, "robot": name, "kind": "edge", "remote": REMOTE})
            files += len(secret_files) + len(edge_files) + 2  # + the two manifest.json
        t4 = time.perf_counter()
        t["bundles"] = t4 - t3
        t["total"] = t4 - t0

        certs = len(fleet.pki.load_index().certs)
        return {
            "seconds": t,
            "fleet_open_s": t_open - t0,
            "key_type": fleet.inventory.vpn.key_type,
            "robots": len(names),
            "certs_in_index": certs,
            "bundle_files_written": files,
            "user_data_bytes_total": ud_bytes,
            "filesystem_dir": str(tmp_path.parent),
        }


# Functions the profile is asked about: (file suffix or "~" for C builtins, function name).
SUSPECTS = {
    "scrypt (hashlib.scrypt)": ("~", "<built-in method _hashlib.scrypt>"),
    "fsync (os.fsync)": ("~", "<built-in method posix.fsync>"),
    "atomic_write": ("ccrp_cli/store.py", "atomic_write"),
    "PkiStore.load_index": ("ccrp_cli/pki/store.py", "load_index"),
    "PkiStore._save_index": ("ccrp_cli/pki/store.py", "_save_index"),
    "PkiStore._ca (load CA cert+key)": ("ccrp_cli/pki/store.py", "_ca"),
    "PkiStore._issue": ("ccrp_cli/pki/store.py", "_issue"),
    "PkiStore.issue_robot": ("ccrp_cli/pki/store.py", "issue_robot"),
    "PkiStore.credentials": ("ccrp_cli/pki/store.py", "credentials"),
    "profiles.generate_key": ("ccrp_cli/pki/profiles.py", "generate_key"),
    "profiles.build_leaf": ("ccrp_cli/pki/profiles.py", "build_leaf"),
    "secrets.hash_password": ("ccrp_cli/pki/secrets.py", "hash_password"),
    "FleetStore.load_state": ("ccrp_cli/store.py", "load_state"),
    "Fleet.load_allocated": ("ccrp_cli/fleet.py", "load_allocated"),
    "Fleet.plan": ("ccrp_cli/fleet.py", "plan"),
    "clone_view": ("ccrp_cli/fleet.py", "clone_view"),
    "cloudinit.user_data": ("ccrp_cli/render/cloudinit.py", "user_data"),
    "bundles.edge_bundle": ("ccrp_cli/render/bundles.py", "edge_bundle"),
    "bundles.write_bundle": ("ccrp_cli/render/bundles.py", "write_bundle"),
}


def profile_once(robots: int, key_type: str | None, tmp_base: str | None) -> dict[str, object]:
    prof = cProfile.Profile()
    t0 = time.perf_counter()
    prof.enable()
    run = run_once(robots, key_type, tmp_base)
    prof.disable()
    wall = time.perf_counter() - t0
    st = pstats.Stats(prof)
    total_tt = sum(v[2] for v in st.stats.values())  # type: ignore[attr-defined]
    suspects = {}
    for label, (where, func) in SUSPECTS.items():
        calls, tt, ct = 0, 0.0, 0.0
        for (file, _line, name), (_cc, nc, t_tt, t_ct, _callers) in st.stats.items():  # type: ignore[attr-defined]
            if name == func and (file == where if where == "~" else file.endswith(where)):
                calls, tt, ct = calls + nc, tt + t_tt, ct + t_ct
        suspects[label] = {"calls": calls, "cumulative_s": round(ct, 4), "self_s": round(tt, 4)}
    top = sorted(st.stats.items(), key=lambda kv: kv[1][2], reverse=True)[:15]  # type: ignore[attr-defined]
    text = io.StringIO()
    pstats.Stats(prof, stream=text).sort_stats("cumulative").print_stats(25)
    return {
        "wall_s_under_profiler": wall,
        "phases_s_under_profiler": run["seconds"],
        "profiled_self_time_s": total_tt,
        "suspects": suspects,
        "top15_self_time": [
            {"function": f"{Path(f).name}:{line}:{name}" if f != "~" else name, "calls": v[1],
             "self_s": round(v[2], 4), "cumulative_s": round(v[3], 4)}
            for (f, line, name), v in top
        ],
        "pstats_cumulative_top25": text.getvalue(),
    }


@contextlib.contextmanager
def patched(patches: list[tuple[object, str, object]]):
    saved = [(obj, attr, getattr(obj, attr)) for obj, attr, _ in patches]
    try:
        for obj, attr, new in patches:
            setattr(obj, attr, new)
        yield
    finally:
        for obj, attr, old in reversed(saved):
            setattr(obj, attr, old)


def instrumented_once(robots: int, key_type: str | None, tmp_base: str | None) -> dict[str, object]:
    """One run with wall-clock timers around the suspects (nested: atomic_write includes fsync)."""
    acc: dict[str, list[float]] = {}

    def timer(label: str, fn):  # noqa: ANN001, ANN202
        acc[label] = [0, 0.0]

        def wrapper(*a, **kw):  # noqa: ANN002, ANN003, ANN202
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                acc[label][0] += 1
                acc[label][1] += time.perf_counter() - t0

        return wrapper

    aw = timer("atomic_write (incl. fsync)", fleet_store.atomic_write)
    me = sys.modules[__name__]
    patches = [
        (pki_store, "hash_password", timer("scrypt hash_password", pki_store.hash_password)),
        (os, "fsync", timer("os.fsync (file + dir)", os.fsync)),
        (fleet_store, "atomic_write", aw),
        (pki_store, "atomic_write", aw),
        (bundles, "atomic_write", aw),
        (pki_store.PkiStore, "load_index", timer("PkiStore.load_index (index.json parse)", pki_store.PkiStore.load_index)),
        (pki_store.PkiStore, "_save_index", timer("PkiStore._save_index (index.json dump+write)", pki_store.PkiStore._save_index)),
        (pki_store.PkiStore, "_ca", timer("PkiStore._ca (CA cert+key load)", pki_store.PkiStore._ca)),
        (pki_store.profiles, "generate_key", timer("profiles.generate_key", pki_store.profiles.generate_key)),
        (pki_store.profiles, "build_leaf", timer("profiles.build_leaf (sign)", pki_store.profiles.build_leaf)),
        (fleet_mod.Fleet, "load_allocated", timer("Fleet.load_allocated (state.json)", fleet_mod.Fleet.load_allocated)),
        (me, "_clone_view", timer("clone_view (incl. Fleet.plan of all robots)", _clone_view)),
        (cloudinit, "dump", timer("cloudinit.dump (yaml.safe_dump)", cloudinit.dump)),
        (cloudinit, "user_data_dict", timer("cloudinit.user_data_dict (templates)", cloudinit.user_data_dict)),
        (bundles, "edge_bundle", timer("bundles.edge_bundle (templates)", bundles.edge_bundle)),
        (bundles, "write_bundle", timer("bundles.write_bundle (incl. atomic_write)", bundles.write_bundle)),
    ]
    with patched(patches):
        run = run_once(robots, key_type, tmp_base)
    return {
        "phases_s": run["seconds"],
        "timers": {k: {"calls": int(v[0]), "seconds": round(v[1], 4)} for k, v in acc.items()},
    }


def what_if(robots: int, key_type: str | None, tmp_base: str | None) -> dict[str, object]:
    """Phase times with fsync and/or scrypt stubbed out (diagnosis only, never how ccrp runs)."""
    stub_hash = pki_secrets.hash_password("stub")
    no_fsync = (os, "fsync", lambda fd: None)
    no_scrypt = (pki_store, "hash_password", lambda password: stub_hash)
    variants = {"no_fsync": [no_fsync], "no_scrypt": [no_scrypt], "no_fsync_no_scrypt": [no_fsync, no_scrypt]}
    out = {}
    for name, patches in variants.items():
        with patched(patches):
            out[name] = run_once(robots, key_type, tmp_base)["seconds"]
    return out


def micro(tmp_base: str | None) -> dict[str, float]:
    """Single-operation costs that explain the phases."""
    out: dict[str, float] = {}
    samples = []
    for _ in range(5):
        t0 = time.perf_counter()
        pki_secrets.hash_password("x" * 32)
        samples.append(time.perf_counter() - t0)
    out["scrypt_hash_password_ms_median"] = statistics.median(samples) * 1000
    from ccrp_cli.store import atomic_write

    with tempfile.TemporaryDirectory(prefix="ccrp-bench-", dir=tmp_base) as tmp:
        samples = []
        for i in range(50):
            t0 = time.perf_counter()
            atomic_write(Path(tmp) / f"f{i}", b"x" * 600)
            samples.append(time.perf_counter() - t0)
    out["atomic_write_600B_ms_median"] = statistics.median(samples) * 1000
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--key-type", choices=["ecdsa-p256", "rsa3072"], default=None,
                    help="default: the inventory's (lab.yaml: ecdsa-p256)")
    ap.add_argument("--profile", action="store_true", help="profile even when the target is met")
    ap.add_argument("--tmp", default=None, help="base dir for the temp dirs (default: $TMPDIR or /tmp)")
    ap.add_argument("--out", type=Path, default=RESULTS / "render_fleet.json")
    args = ap.parse_args()

    runs = []
    for i in range(args.repeat):
        run = run_once(args.robots, args.key_type, args.tmp)
        runs.append(run)
        s = run["seconds"]
        print(f"  run {i + 1}: total {s['total']:.2f}s  " + "  ".join(f"{p} {s[p]:.2f}s" for p in PHASES), flush=True)

    median = {k: statistics.median(r["seconds"][k] for r in runs) for k in (*PHASES, "total")}
    ok = median["total"] < TARGET_S
    tmp_dir = runs[0]["filesystem_dir"]
    fs = subprocess.run(["df", "--output=fstype", tmp_dir], capture_output=True, text=True).stdout.split()
    result: dict[str, object] = {
        "benchmark": "render_fleet",
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "temp_dir": tmp_dir,
            "temp_fs": fs[-1] if fs else None,
        },
        "robots": args.robots,
        "repeat": args.repeat,
        "key_type": runs[0]["key_type"],
        "median_s": median,
        "target_total_s": TARGET_S,
        "target_ok": ok,
        "runs": runs,
        "micro": micro(args.tmp),
    }
    if not ok or args.profile:
        print("  profiling one more run (cProfile)...", flush=True)
        result["profile"] = profile_once(args.robots, args.key_type, args.tmp)
        print("  one instrumented run and three what-if runs...", flush=True)
        result["instrumented"] = instrumented_once(args.robots, args.key_type, args.tmp)
        result["what_if"] = what_if(args.robots, args.key_type, args.tmp)

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")

    print(f"render_fleet: {args.robots} robots, {runs[0]['key_type']}, median of {args.repeat} runs, "
          f"python {platform.python_version()}, {os.cpu_count()} cpus, temp fs {result['machine']['temp_fs']}")
    print("  " + "  ".join(f"{p} {median[p]:.2f}s" for p in PHASES))
    print(f"  total {median['total']:.2f}s (target < {TARGET_S:.0f}s): {'OK' if ok else 'MISSED'}")
    m = result["micro"]
    print(f"  one scrypt hash {m['scrypt_hash_password_ms_median']:.0f} ms, "
          f"one atomic_write {m['atomic_write_600B_ms_median']:.2f} ms")
    if "profile" in result:
        prof = result["profile"]
        print(f"  cProfile run: {prof['wall_s_under_profiler']:.2f}s wall (profiler overhead included)")
        for label, v in prof["suspects"].items():
            if v["calls"]:
                print(f"    {label:<34}{v['calls']:>6} calls {v['cumulative_s']:>8.3f}s cumulative")
        ins = result["instrumented"]
        print(f"  instrumented run (no profiler): total {ins['phases_s']['total']:.2f}s; time inside:")
        for label, v in sorted(ins["timers"].items(), key=lambda kv: kv[1]["seconds"], reverse=True):
            print(f"    {label:<46}{v['calls']:>6} calls {v['seconds']:>7.3f}s")
        print("  what-if (stubbed in this process only):")
        for name, s in result["what_if"].items():
            print(f"    {name:<20} total {s['total']:.2f}s  " + "  ".join(f"{p} {s[p]:.2f}s" for p in PHASES))
    print(f"  -> {args.out.relative_to(ROOT) if args.out.is_relative_to(ROOT) else args.out}")


if __name__ == "__main__":
    sys.exit(main())
