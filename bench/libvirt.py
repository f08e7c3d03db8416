"""libvirt VM clones beside Docker container clones, in one run, through ccrp's own CLI and provider
classes (issue 27). One fleet of one robot per backend (nao1, ROS 1 Noetic: the distro whose golden
volume is built and booted on libvirt), measured one after the other so they do not share the CPUs:

  snapshot_build_s   `ccrp snapshot build`: libvirt: the recipe's image, then the golden volume
                     (goldens.py) uploaded to the pool; Docker: the recipe's image (layer cache)
  ready              `ccrp fleet up --json`: the clone's seconds (created from the snapshot until its
                     VPN server is up and its master answers) and the command's wall time
  disk_mb            libvirt: the clone's qcow2 overlay's allocation after that (LibvirtProvider.
                     footprint); Docker: the container's RW layer (inspect SizeRw)
  memory_mib         libvirt: the QEMU process's RSS (virDomainMemoryStats rss); Docker: the
                     container's cgroup usage minus inactive file pages (as `docker stats`)
  overlay_create_s   libvirt only: LibvirtProvider.create_overlay (pool.createXML of a qcow2 backed
                     by the golden volume), --overlays times, each deleted after
  bare               --bare (libvirt): `snapshot build --bare` (systemd + cloud-init only) and
                     `fleet up` of a clone whose cloud-init installs the recipe at boot, with
                     --bare-timeout; its failure is recorded as measured, not retried

The fleets are `lvb<random>` and `dkb<random>` with pools nothing of this host uses (as `ccrp init`
picks them), in their own CCRP_HOME; everything they make (domains, volumes, golden volumes,
networks, containers, images) is removed at the end, even on failure. The machine's load average
is recorded before and after: TCG boots slow down several times under load.

Run: .venv/bin/python bench/libvirt.py [--accel auto] [--memory-mb 1536] [--vcpus 2] [--overlays 5]
                                       [--bare] [--bare-timeout 1800] [--out PATH]
Needs libvirtd (bash scripts/libvirt.sh) and a Docker engine. Writes bench/results/libvirt.json.
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

# Run as a script, this file's directory is sys.path[0], and this file is named libvirt.py: the
# provider's `import libvirt` would import it instead of the binding.
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
TAG = "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(5))
LV, DK = f"lvb{TAG}", f"dkb{TAG}"
ROBOT = "nao1"


def progress(msg: str) -> None:
    print(f"bench {time.strftime('%H:%M:%S')}: {msg}", file=sys.stderr, flush=True)


def inventories(args, distro: str = "noetic", robot: str = ROBOT, lv: str = LV, dk: str = DK) -> dict[str, dict]:
    """The libvirt fleet `lv` and the Docker fleet `dk`, one robot each (also bench/openstack_real.py's)."""
    # Pools no route, Docker or libvirt network, or fleet of this host overlaps: as `ccrp init`
    # picks them; free() takes each it returns, so the two fleets get different ones.
    from ccrp_cli.ops.init import free, used_networks

    used = used_networks()
    base = {"ros": {"distro": distro}, "robots": [{"name": robot}]}
    return {
        lv: {"fleet": lv, "provider": {"kind": "libvirt", "accel": args.accel, "memory_mb": args.memory_mb,
                                       "vcpus": args.vcpus, "public_cidr": free("public", used)},
             "vpn": {"pool": free("vpn", used)}, "common": {"cidr": free("common", used)}, **base},
        dk: {"fleet": dk, "provider": {"kind": "docker", "public_cidr": free("public", used)},
             "vpn": {"pool": free("vpn", used)}, "common": {"cidr": free("common", used)}, **base},
    }


class Cli:
    def __init__(self, home: Path, inventory: Path) -> None:
        self.env = {**os.environ, "CCRP_HOME": str(home)}
        self.env.pop("CCRP_INVENTORY", None)
        self.inventory = str(inventory)

    def run(self, *args: str, timeout: float = 3600) -> tuple[float, subprocess.CompletedProcess]:
        argv = [sys.executable, "-m", "ccrp_cli", *args, "-i", self.inventory]
        t0 = time.perf_counter()
        proc = subprocess.run(argv, env=self.env, capture_output=True, text=True, timeout=timeout, cwd=ROOT)
        return time.perf_counter() - t0, proc

    def __call__(self, *args: str, timeout: float = 3600):
        """`ccrp ARGS -i INVENTORY`: (wall seconds, parsed --json output or None); a failure ends the run."""
        wall, proc = self.run(*args, timeout=timeout)
        if proc.returncode != 0:
            raise SystemExit(f"ccrp {' '.join(args)} failed ({proc.returncode}): {proc.stderr.strip()[-800:]}")
        out = proc.stdout.strip()
        return wall, (json.loads(out) if out.startswith(("[", "{")) else None)


def provider_of(home: Path, inventory: Path):
    """The fleet and its provider in this process, as the CLI opens them."""
    os.environ["CCRP_HOME"] = str(home)
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.providers import get_provider

    fleet = Fleet.open(inventory)
    return fleet, get_provider(fleet.inventory)


def ready(rows: list[dict], wall: float, robot: str = ROBOT) -> dict:
    [row] = [r for r in rows if r["robot"] == robot]
    if row["action"] != "created":
        raise SystemExit(f"fleet up did not create {robot}'s clone: {row}")
    return {"clone_s": row["seconds"], "wall_s": round(wall, 1)}


def overlay_times(provider, image: str, n: int) -> list[float]:
    """LibvirtProvider.create_overlay of `n` overlays of the golden volume, timed one by one."""
    from ccrp_cli.providers.libvirt import images

    c = provider.client
    pool = c.pool()
    disk_path = images.golden(c, image)[0]
    times = []
    for k in range(n):
        name = f"{c.domain_name(f'ovl{k}')}.qcow2"  # a clone volume's name: `ccrp gc` finds a leftover
        t0 = time.perf_counter()
        provider.create_overlay(pool, name, image, disk_path)
        times.append(round(time.perf_counter() - t0, 4))
        c.delete_vol(c.refreshed(pool), name)
    return times


def docker_measures(fleet: str, robot: str = ROBOT) -> dict:
    """The clone container's RW layer and memory, as `docker ps --size` and `docker stats` give them."""
    import docker

    client = docker.from_env()
    try:
        name = f"ccrp-{fleet}-cri-{robot}"
        [size] = client.api.containers(all=True, size=True, filters={"name": f"^/{name}$"})  # GET /containers/json?size=1
        mem = client.containers.get(name).stats(stream=False)["memory_stats"]
        inactive = mem.get("stats", {}).get("inactive_file", mem.get("stats", {}).get("total_inactive_file", 0))
        return {"disk_mb": round(size.get("SizeRw", 0) / 1e6, 1), "image_mb": round(size.get("SizeRootFs", 0) / 1e6, 1),
                "memory_mib": round((mem["usage"] - inactive) / (1 << 20), 1)}
    finally:
        client.close()


def cleanup_docker(fleets: list[str]) -> None:
    """What ccrp labelled with the bench fleets on the Docker engine (containers, networks, volumes,
    images: the libvirt fleet's recipe image is Docker's too), as docker_fleet.py cleans its own
    (loaded by path: this file's directory is off sys.path, above)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("docker_fleet", Path(__file__).with_name("docker_fleet.py"))
    docker_fleet = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(docker_fleet)
    for fleet in fleets:
        docker_fleet.cleanup_fleet(fleet)


def remove_snapshots(provider, fleet: str) -> list[str]:
    """The fleet's snapshots deleted (after its `fleet down`), the provider closed; the names of
    what is left of the fleet, said on stderr."""
    try:
        for snap in provider.list_snapshots():
            provider.delete_snapshot(snap.id)
        left = [r.name for r in provider.list_owned()]
        if left:
            progress(f"left of {fleet}: {left}")
        return left
    finally:
        provider.close()


def load() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--accel", default="auto", choices=("auto", "kvm", "tcg"))
    ap.add_argument("--memory-mb", type=int, default=1536)
    ap.add_argument("--vcpus", type=int, default=2)
    ap.add_argument("--overlays", type=int, default=5)
    ap.add_argument("--bare", action="store_true", help="also a clone from a bare golden volume (libvirt)")
    ap.add_argument("--bare-timeout", type=float, default=1800)
    ap.add_argument("--out", type=Path, help="write the JSON here instead of bench/results/libvirt.json")
    args = ap.parse_args()
    result: dict = {"benchmark": "libvirt", "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                    "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release()},
                    "load_before": load(), "fleets": {"libvirt": LV, "docker": DK}}
    lv_provider = None
    with tempfile.TemporaryDirectory(prefix="ccrp-bench-lv-") as tmp:
        home = Path(tmp) / "home"
        paths = {}
        for name, inv in inventories(args).items():
            paths[name] = Path(tmp) / f"{name}.yaml"
            paths[name].write_text(yaml.safe_dump(inv, sort_keys=False))
        lv, dk = Cli(home, paths[LV]), Cli(home, paths[DK])
        try:
            lv("vpn", "init")
            dk("vpn", "init")
            progress("libvirt: snapshot build (the recipe's image, the golden volume)")
            wall, built = lv("snapshot", "build", "--json")
            lv_build = {"wall_s": round(wall, 1), "golden_mb": built[0]["size_mb"]}
            progress(f"libvirt: golden volume in {wall:.1f} s")
            wall, built = dk("snapshot", "build", "--json")
            dk_build = {"wall_s": round(wall, 1), "image_mb": built[0]["size_mb"]}
            progress(f"docker: snapshot image in {wall:.1f} s")

            _fleet, lv_provider = provider_of(home, paths[LV])
            golden = json.loads((home / LV / "state.json").read_text())["snapshot"]["image"]
            overlays = overlay_times(lv_provider, golden, args.overlays)
            progress(f"libvirt: {len(overlays)} overlays, median {statistics.median(overlays):.3f} s")

            # Docker first, alone; then the VM, alone.
            wall, rows = dk("fleet", "up", "--json")
            docker_clone = {"ready": ready(rows, wall), **docker_measures(DK)}
            progress(f"docker: clone ready in {docker_clone['ready']['clone_s']} s")
            dk("fleet", "down")

            load_boot = load()
            wall, rows = lv("fleet", "up", "--json", timeout=7200)
            vm_clone = {"ready": ready(rows, wall), "load_at_start": load_boot, "load_at_ready": load(),
                        "accel": json.loads((home / LV / "libvirt-accel.json").read_text()).get("qemu:///system")
                        if (home / LV / "libvirt-accel.json").exists() else args.accel,
                        **{k.replace("overlay_mb", "disk_mb").replace("rss_mib", "memory_mib"): v
                           for k, v in lv_provider.footprint(ROBOT).items()}}
            progress(f"libvirt: clone ready in {vm_clone['ready']['clone_s']} s ({vm_clone})")
            lv("fleet", "down")

            bare = None
            if args.bare:
                progress("libvirt: bare golden volume")
                wall, built = lv("snapshot", "build", "--bare", "--json")
                bare = {"build_wall_s": round(wall, 1), "golden_mb": built[0]["size_mb"]}
                try:
                    wall, proc = lv.run("fleet", "up", "--json", timeout=args.bare_timeout)
                except subprocess.TimeoutExpired:  # the clone is left to the `fleet down` below
                    bare |= {"wall_s": args.bare_timeout, "action": "timed out"}
                else:
                    rows = json.loads(proc.stdout) if proc.stdout.strip().startswith("[") else []
                    row = next((r for r in rows if r["robot"] == ROBOT), {})
                    bare |= {"wall_s": round(wall, 1), "action": row.get("action"), "clone_s": row.get("seconds"),
                             "detail": (row.get("detail") or proc.stderr.strip()[-400:])[:400]}
                progress(f"libvirt: bare clone {bare['action']} after {bare['wall_s']:.1f} s")
                lv("fleet", "down")
        finally:
            try:
                lv.run("fleet", "down")
                dk.run("fleet", "down")
                if lv_provider is not None:
                    remove_snapshots(lv_provider, LV)
            finally:
                cleanup_docker([LV, DK])

    result |= {
        "load_after": load(),
        "libvirt": {"snapshot_build": lv_build, "overlay_create_s": {"median": statistics.median(overlays),
                                                                     "samples": overlays},
                    "clone": vm_clone, "memory_mb_given": args.memory_mb, "vcpus": args.vcpus}
        | ({"bare": bare} if bare else {}),
        "docker": {"snapshot_build": dk_build, "clone": docker_clone},
    }
    result["ratios"] = {
        "ready_vm_over_container": round(vm_clone["ready"]["clone_s"] / docker_clone["ready"]["clone_s"], 1),
        "disk_vm_over_container": round(vm_clone["disk_mb"] / docker_clone["disk_mb"], 1) if docker_clone["disk_mb"] else None,
        "memory_vm_over_container": round(vm_clone["memory_mib"] / docker_clone["memory_mib"], 1),
    }
    if bare and bare.get("clone_s"):
        result["ratios"]["ready_bare_over_snapshot_vm"] = round(bare["clone_s"] / vm_clone["ready"]["clone_s"], 1)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (args.out or RESULTS / "libvirt.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
