"""A real OpenStack (scripts/openstack.sh's all-in-one Zed) beside the Docker and libvirt backends,
in one run (issue 40). One robot (r1, ROS 2 Jazzy) per backend, one backend after the other (they
share this host's cores):

  aio                the services' memory at rest (`scripts/openstack.sh --status`: each service's
                     RSS with its children, the total, the Nova guests running), at the start and at
                     the end; with --restart also the times of `scripts/openstack.sh --down` and of
                     the start after it (off by default: it stops the cloud for everyone using it)
  openstack          a fleet `osb<random>` from `ccrp init --provider openstack` (cloud ccrp-aio,
                     flavor ccrp.small, operator_cidr 198.51.100.1/32), its commands run in this
                     process so that every HTTP request of openstacksdk is counted
                     (keystoneauth1.session.Session.request wrapped; by service from the port:
                     5000 keystone, 8774 nova, 9696 neutron, 9292 glance, 8778 placement; and by
                     method and path with ids as {id}): `ccrp doctor` (and within it the quota
                     check, OpenStackProvider.quotas), `ccrp snapshot bake`, `ccrp clone create
                     --robot r1 --json` (ccrp's seconds to serving, the wall time, its calls, the
                     quota check's among them, and the guest's QEMU RSS read from libvirt by the
                     server's id), `ccrp clone delete`, `ccrp fleet down`, `ccrp snapshot delete
                     <id> --force`; then openstacksdk (uncounted) checks that no server, port,
                     floating IP, security group, router, network, subnet, key pair or image of the
                     fleet is left
  docker, libvirt    `ccrp snapshot build` and `ccrp fleet up --json` of the same one-robot Jazzy
                     fleet on each (bench/libvirt.py's functions: subprocesses of the CLI, its
                     clone's seconds and the command's wall time; disk and memory as there); the
                     libvirt VM gets the flavor's shape (--libvirt-vcpus 1, --libvirt-memory-mb 1536)
  ratios             OpenStack's clone-ready seconds over Docker's and over libvirt's

Everything made is removed at the end, even on failure: the OpenStack fleet by `ccrp fleet down` and
its snapshots deleted, the others as bench/libvirt.py removes them. Only resources named or tagged
with the bench's own fleets are touched (others run fleets on the same cloud). The machine (cores,
RAM) and its load average before and after each clone are recorded.

Run: CCRP_OPENSTACK_TIMEOUT_SCALE=6 .venv/bin/python bench/openstack_real.py [--restart]
         [--parts aio,openstack,docker,libvirt] [--doctor-only] [--out PATH]
Needs scripts/openstack.sh's cloud (clouds.yaml entry ccrp-aio), libvirtd and a Docker engine.
Writes bench/results/openstack_real.json.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import datetime as dt
import importlib.util
import io
import json
import os
import platform
import re
import secrets
import string
import subprocess
import sys
import tempfile
import threading
import time
import types
from pathlib import Path
from urllib.parse import urlsplit

# This file's directory holds bench/libvirt.py, which `import libvirt` must not find (as there).
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import yaml  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def _bench(name: str) -> types.ModuleType:
    """bench/<name>.py loaded by path, as bench_<name> (a bench file is no package's module)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", Path(__file__).with_name(f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


lvb = _bench("libvirt")
progress, load, Cli, ready = lvb.progress, lvb.load, lvb.Cli, lvb.ready

TAG = "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(5))
OS, LV, DK = f"osb{TAG}", f"lvb{TAG}", f"dkb{TAG}"
ROBOT = "r1"
DISTRO = "jazzy"
CLOUD, FLAVOR, OPERATOR = "ccrp-aio", "ccrp.small", "198.51.100.1/32"
PORTS = {5000: "keystone", 8774: "nova", 8775: "nova-metadata", 9696: "neutron", 9292: "glance", 8778: "placement"}
ID = re.compile(r"/(?:[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}|[0-9a-f]{32})(?=/|$)")


# -- the machine and the all-in-one cloud ------------------------------------------------------------
def machine() -> dict:
    mem = dict(line.split(":", 1) for line in Path("/proc/meminfo").read_text().splitlines() if ":" in line)
    return {"cpus": os.cpu_count(), "ram_gib": round(int(mem["MemTotal"].split()[0]) / (1 << 20), 1),
            "python": platform.python_version(), "kernel": platform.release()}


def aio_status() -> dict:
    """`bash scripts/openstack.sh --status`: each service's pid, port and RSS (MB, with its
    children), the total and the Nova guests running, as the script prints them."""
    proc = subprocess.run(["bash", "scripts/openstack.sh", "--status"], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    services, total, guests = {}, None, None
    for line in proc.stdout.splitlines():
        parts = line.split()
        if len(parts) == 4 and parts[3].isdigit() and parts[0] != "SERVICE":
            services[parts[0]] = {"pid": int(parts[1]) if parts[1].isdigit() else None,
                                  "port": int(parts[2]) if parts[2].isdigit() else None, "rss_mb": int(parts[3])}
        elif m := re.search(r"total RSS of the services: (\d+) MB; Nova guests running: (\d+)", line):
            total, guests = int(m[1]), int(m[2])
    if proc.returncode != 0 or total is None:
        raise SystemExit(f"openstack.sh --status failed ({proc.returncode}): {(proc.stdout + proc.stderr)[-600:]}")
    return {"services": services, "total_rss_mb": total, "nova_guests_running": guests,
            "free_mib": free_mib(), "load": load()}


def free_mib() -> dict:
    mem = {k: int(v.split()[0]) for k, v in (line.split(":", 1) for line in Path("/proc/meminfo").read_text().splitlines())}
    return {"used": round((mem["MemTotal"] - mem["MemAvailable"]) / 1024), "available": round(mem["MemAvailable"] / 1024)}


def aio_restart() -> dict:
    """`scripts/openstack.sh --down`, then `scripts/openstack.sh`, each timed."""
    out = {}
    for key, argv in (("down_s", ["--down"]), ("start_s", [])):
        t0 = time.perf_counter()
        proc = subprocess.run(["bash", "scripts/openstack.sh", *argv], cwd=ROOT, capture_output=True, text=True,
                              timeout=1800)
        out[key] = round(time.perf_counter() - t0, 1)
        progress(f"openstack.sh {' '.join(argv) or '(start)'}: {out[key]} s, exit {proc.returncode}")
        if proc.returncode != 0:
            raise SystemExit(f"openstack.sh {' '.join(argv)} failed: {(proc.stdout + proc.stderr)[-800:]}")
    return out


# -- HTTP requests of openstacksdk, counted ----------------------------------------------------------
class ApiCounter:
    """Every keystoneauth1 Session.request (each SDK call, each token request, each version
    discovery; a request keystoneauth retries itself is one) while `active`, by service, method
    and path; those made inside OpenStackProvider.quotas (in the same thread) also as `quota`."""

    def __init__(self) -> None:
        self.active = False
        self.calls: list[dict] = []
        self._lock = threading.Lock()
        self._local = threading.local()

    def install(self) -> None:
        from keystoneauth1.session import Session

        from ccrp_cli.providers.openstack.provider import OpenStackProvider

        counter, request, quotas = self, Session.request, OpenStackProvider.quotas

        def counted_request(session, url, method, *args, **kwargs):
            if not counter.active:
                return request(session, url, method, *args, **kwargs)
            try:
                resp = request(session, url, method, *args, **kwargs)
            except Exception as exc:
                counter.record(getattr(exc, "url", None) or url, method, getattr(exc, "http_status", None) or type(exc).__name__)
                raise
            counter.record(resp.url, method, resp.status_code)
            return resp

        def counted_quotas(provider, *args, **kwargs):
            depth = getattr(counter._local, "quota", 0)
            counter._local.quota = depth + 1
            try:
                return quotas(provider, *args, **kwargs)
            finally:
                counter._local.quota = depth

        Session.request = counted_request
        OpenStackProvider.quotas = counted_quotas

    def record(self, url: str, method: str, status) -> None:
        parts = urlsplit(url)
        service = PORTS.get(parts.port, f"port {parts.port}") if parts.port else "?"
        path = ID.sub("/{id}", parts.path) or "/"
        with self._lock:
            self.calls.append({"service": service, "method": method.upper(), "path": path, "status": status,
                               "quota": bool(getattr(self._local, "quota", 0))})

    @contextlib.contextmanager
    def measuring(self):
        """The calls made inside, summarised into the dict yielded (filled on exit)."""
        summary: dict = {}
        start = len(self.calls)
        self.active = True
        try:
            yield summary
        finally:
            self.active = False
            summary.update(summarise(self.calls[start:]))


def summarise(calls: list[dict]) -> dict:
    def counts(rows):
        by_service = collections.Counter(c["service"] for c in rows)
        by_method = collections.Counter(f"{c['service']} {c['method']}" for c in rows)
        return {"total": len(rows), "by_service": dict(by_service.most_common()),
                "by_method": dict(by_method.most_common())}

    by_path = collections.Counter(f"{c['service']} {c['method']} {c['path']}" for c in calls)
    errors = collections.Counter(f"{c['service']} {c['method']} {c['path']} {c['status']}" for c in calls
                                 if not (isinstance(c["status"], int) and c["status"] < 400))
    quota = [c for c in calls if c["quota"]]
    return {**counts(calls), "by_path": dict(by_path.most_common()), "errors": dict(errors.most_common()),
            "quota_check": counts(quota) | {"by_path": dict(collections.Counter(
                f"{c['service']} {c['method']} {c['path']}" for c in quota).most_common())}}


class Tee(io.StringIO):
    """Keeps what is written and passes it to the real stream (ccrp's lines show while a command runs)."""

    def __init__(self, stream) -> None:
        super().__init__()
        self.stream = stream

    def write(self, s: str) -> int:
        self.stream.write(s)
        self.stream.flush()
        return super().write(s)


def ccrp_inprocess(*args: str, home: Path, env: dict[str, str]) -> tuple[int, str, str, float]:
    """(exit code, stdout, stderr, wall seconds) of `ccrp ARGS` run in this process through its
    console entry point (tests/inprocess_cli.py), stderr also passed through."""
    from tests.inprocess_cli import run_ccrp_inprocess

    t0 = time.perf_counter()
    code, out, err = run_ccrp_inprocess(*args, home=home, env=env, err=Tee(sys.stderr))
    return code, out, err, time.perf_counter() - t0


# -- what is left of a fleet on the cloud, seen with openstacksdk -----------------------------------
def leftovers(fleet: str) -> dict[str, list[str]]:
    """Everything on the cloud named ccrp-<fleet>-... or carrying the tag ccrp-fleet=<fleet> (or
    that image property): servers, ports, floating IPs, security groups, routers, networks,
    subnets, key pairs, images. Read only."""
    import openstack

    conn = openstack.connect(cloud=CLOUD)
    prefix, tag = f"ccrp-{fleet}", f"ccrp-fleet={fleet}"

    def ours(res) -> bool:
        name = getattr(res, "name", None) or ""
        return (name == prefix or name.startswith(prefix + "-") or tag in (getattr(res, "tags", None) or [])
                or (getattr(res, "metadata", None) or {}).get("ccrp-fleet") == fleet
                or (getattr(res, "properties", None) or {}).get("ccrp-fleet") == fleet)

    try:
        found = {
            "servers": [s.name for s in conn.compute.servers() if ours(s)],
            "ports": [p.name or p.id for p in conn.network.ports() if ours(p)],
            "floating_ips": [f.floating_ip_address for f in conn.network.ips() if ours(f)],
            "security_groups": [g.name for g in conn.network.security_groups() if ours(g)],
            "routers": [r.name for r in conn.network.routers() if ours(r)],
            "networks": [n.name for n in conn.network.networks() if ours(n)],
            "subnets": [n.name for n in conn.network.subnets() if ours(n)],
            "keypairs": [k.name for k in conn.compute.keypairs() if ours(k)],
            "images": [i.name for i in conn.image.images() if ours(i)],
        }
    finally:
        conn.close()
    return {k: v for k, v in found.items() if v}


def guest_rss_mib(server_name: str) -> float | None:
    """The QEMU RSS of the Nova guest named so (Nova names the libvirt domain's UUID after the
    server's id), from the host's libvirtd; None if not found."""
    import libvirt
    import openstack

    conn = openstack.connect(cloud=CLOUD)
    try:
        server = conn.compute.find_server(server_name)
        if server is None:
            return None
        virt = libvirt.open("qemu:///system")
        try:
            return round(virt.lookupByUUIDString(server.id).memoryStats().get("rss", 0) / 1024, 1)
        finally:
            virt.close()
    except Exception as exc:  # noqa: BLE001 - an extra figure: its absence is recorded, not fatal
        progress(f"guest RSS of {server_name}: {exc}")
        return None
    finally:
        conn.close()


# -- the OpenStack fleet ------------------------------------------------------------------------------
def openstack_part(tmp: Path, counter: ApiCounter, doctor_only: bool, res: dict) -> None:
    """Measured into `res` step by step (what a failure leaves is kept)."""
    home, inventory = tmp / "home", tmp / "ccrp.yaml"
    env = {"CCRP_OPENSTACK_TIMEOUT_SCALE": os.environ.get("CCRP_OPENSTACK_TIMEOUT_SCALE", "6")}
    res |= {"fleet": OS, "cloud": CLOUD, "flavor": FLAVOR, "timeout_scale": int(env["CCRP_OPENSTACK_TIMEOUT_SCALE"])}

    def ccrp(*args: str, check: bool = True) -> tuple[int, str, float]:
        code, out, err, wall = ccrp_inprocess(*args, "-i", str(inventory), home=home, env=env)
        if check and code != 0:
            raise SystemExit(f"ccrp {' '.join(args)} failed ({code}): {err.strip()[-800:]}")
        return code, out, wall

    import inspect

    from ccrp_cli.cli.init import init

    # A ccrp whose init takes --cloud asks that cloud for the flavor, network and this host's address.
    cloud = ["--cloud", CLOUD] if "cloud" in inspect.signature(init).parameters else []
    code, _out, err, _wall = ccrp_inprocess("init", "--provider", "openstack", "--robots", ROBOT, "--fleet", OS,
                                            "--distro", DISTRO, *cloud, "-o", str(inventory), home=home, env=env)
    if code != 0:
        raise SystemExit(f"ccrp init failed: {err}")
    inv = yaml.safe_load(inventory.read_text())
    inv["provider"] |= {"cloud": CLOUD, "flavor": FLAVOR, "operator_cidr": OPERATOR}
    inventory.write_text(yaml.safe_dump(inv, sort_keys=False))
    try:
        with counter.measuring() as calls:
            code, out, wall = ccrp("doctor", "--json", check=False)
        checks = json.loads(out) if out.strip().startswith("[") else []
        res["doctor"] = {"exit": code, "wall_s": round(wall, 2), "calls": calls,
                         "quota_lines": [c for c in checks if "quota" in str(c.get("check", "")).lower()],
                         "not_ok": [c for c in checks if c.get("status") not in ("ok", None)]}
        progress(f"openstack: doctor {wall:.1f} s, {calls['total']} calls, quota check {calls['quota_check']['total']}")
        if doctor_only:
            return

        progress("openstack: snapshot bake")
        with counter.measuring() as calls:
            _code, out, wall = ccrp("snapshot", "bake", "--json")
        [snap] = json.loads(out)
        snapshot_id = snap["id"]  # deleted below, or by remove_snapshots after a failure
        res["snapshot_bake"] = {"wall_s": round(wall, 1), "image_mb": snap.get("size_mb"), "name": snap["name"],
                                "calls": calls}
        progress(f"openstack: bake {wall:.1f} s, {calls['total']} calls")

        load_start = load()
        progress("openstack: clone create")
        with counter.measuring() as calls:
            _code, out, wall = ccrp("clone", "create", "--robot", ROBOT, "--json")
        rows = json.loads(out)
        res["clone"] = {"ready": ready(rows, wall, ROBOT), "load_at_start": load_start, "load_at_ready": load(),
                        "memory_mib": guest_rss_mib(f"ccrp-{OS}-cri-{ROBOT}"), "calls": calls}
        progress(f"openstack: clone ready in {res['clone']['ready']['clone_s']} s, {calls['total']} calls")

        with counter.measuring() as calls:
            _code, out, wall = ccrp("clone", "delete", "--robot", ROBOT, "--json")
        res["clone_delete"] = {"wall_s": round(wall, 1), "result": json.loads(out), "calls": calls}
        with counter.measuring() as calls:
            _code, out, wall = ccrp("fleet", "down", "--json")
        res["fleet_down"] = {"wall_s": round(wall, 1), "result": json.loads(out) if out.strip() else None,
                             "calls": calls}
        with counter.measuring() as calls:
            _code, out, wall = ccrp("snapshot", "delete", snapshot_id, "--force")
        res["snapshot_delete"] = {"wall_s": round(wall, 1), "calls": calls}
    finally:
        counter.active = False
        if "fleet_down" not in res and not (doctor_only and "doctor" in res):
            ccrp("fleet", "down", check=False)
        if (home / OS).exists() and not doctor_only:  # its snapshots, whatever step stopped
            try:
                _fleet, provider = lvb.provider_of(home, inventory)
                lvb.remove_snapshots(provider, OS)
            except BaseException as exc:  # noqa: BLE001 - the leftover check below says what stayed
                progress(f"openstack: removing {OS}'s snapshots: {exc}")
        res["left"] = leftovers(OS)
        progress(f"openstack: left of {OS}: {res['left'] or 'nothing'}")


# -- Docker and libvirt (bench/libvirt.py's way) ----------------------------------------------------
def local_part(tmp: Path, args, kinds: list[str], out: dict) -> None:
    """Each of `kinds` measured into out[kind] as it finishes."""
    home = tmp / "home"
    shape = types.SimpleNamespace(accel=args.accel, memory_mb=args.libvirt_memory_mb, vcpus=args.libvirt_vcpus)
    invs = lvb.inventories(shape, distro=DISTRO, robot=ROBOT, lv=LV, dk=DK)
    clis = {}
    for kind, name in (("docker", DK), ("libvirt", LV)):
        if kind in kinds:
            path = tmp / f"{name}.yaml"
            path.write_text(yaml.safe_dump(invs[name], sort_keys=False))
            clis[kind] = Cli(home, path)
    lv_provider = None
    try:
        for kind, cli in clis.items():  # one after the other: never two clones at once
            fleet = DK if kind == "docker" else LV
            cli("vpn", "init")
            progress(f"{kind}: snapshot build")
            wall, built = cli("snapshot", "build", "--json")
            build = {"wall_s": round(wall, 1), "size_mb": built[0]["size_mb"]}
            load_start = load()
            progress(f"{kind}: fleet up")
            wall, rows = cli("fleet", "up", "--json", timeout=7200)
            clone = {"ready": ready(rows, wall, ROBOT), "load_at_start": load_start, "load_at_ready": load()}
            if kind == "docker":
                clone |= lvb.docker_measures(DK, ROBOT)
            else:
                _fleet, lv_provider = lvb.provider_of(home, clis["libvirt"].inventory)
                clone |= {k.replace("overlay_mb", "disk_mb").replace("rss_mib", "memory_mib"): v
                          for k, v in lv_provider.footprint(ROBOT).items()}
                clone["vcpus"], clone["memory_mb_given"] = args.libvirt_vcpus, args.libvirt_memory_mb
            progress(f"{kind}: clone ready in {clone['ready']['clone_s']} s (command {clone['ready']['wall_s']} s)")
            cli("fleet", "down")
            out[kind] = {"fleet": fleet, "snapshot_build": build, "clone": clone}
    finally:
        try:
            for cli in clis.values():
                cli.run("fleet", "down")
            if "libvirt" in clis:
                if lv_provider is None:
                    _fleet, lv_provider = lvb.provider_of(home, clis["libvirt"].inventory)
                lvb.remove_snapshots(lv_provider, LV)
        finally:
            lvb.cleanup_docker([f for k, f in (("docker", DK), ("libvirt", LV)) if k in clis])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--restart", action="store_true",
                    help="time scripts/openstack.sh --down and the start after it (stops the cloud for everyone)")
    ap.add_argument("--parts", default="aio,openstack,docker,libvirt")
    ap.add_argument("--doctor-only", action="store_true", help="of the OpenStack fleet, `ccrp doctor` only")
    ap.add_argument("--accel", default="auto", choices=("auto", "kvm", "tcg"))
    ap.add_argument("--libvirt-vcpus", type=int, default=1, help="1: as the flavor ccrp.small")
    ap.add_argument("--libvirt-memory-mb", type=int, default=1536, help="1536: as the flavor ccrp.small")
    ap.add_argument("--out", type=Path, help="write the JSON here instead of bench/results/openstack_real.json")
    args = ap.parse_args()
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    out_path = args.out or RESULTS / "openstack_real.json"
    result: dict = {"benchmark": "openstack_real", "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                    "command": " ".join(["bench/openstack_real.py", *sys.argv[1:]]), "machine": machine(),
                    "load_before": load(), "fleets": {"openstack": OS, "docker": DK, "libvirt": LV}}

    def write(final: bool) -> None:
        result["complete"] = final
        out_path.parent.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(result, indent=2) + "\n")

    counter = ApiCounter()
    try:
        if "aio" in parts:
            result["aio"] = {"at_rest_before": aio_status()}
            progress(f"aio: {result['aio']['at_rest_before']['total_rss_mb']} MB RSS, "
                     f"{result['aio']['at_rest_before']['nova_guests_running']} guests")
            if args.restart:
                result["aio"]["restart"] = aio_restart()
                result["aio"]["after_restart"] = aio_status()
        # A part that fails is recorded and the next runs: each removes what it made itself.
        if "openstack" in parts:
            counter.install()
            result["openstack"] = {}
            with tempfile.TemporaryDirectory(prefix="ccrp-bench-os-") as tmp:
                try:
                    openstack_part(Path(tmp), counter, args.doctor_only, result["openstack"])
                except Exception as exc:  # SystemExit included: ccrp's own failure line
                    result["openstack"]["error"] = str(exc)[-1000:]
                    progress(f"openstack: FAILED: {exc}")
                except SystemExit as exc:
                    result["openstack"]["error"] = str(exc)[-1000:]
                    progress(f"openstack: FAILED: {exc}")
                finally:
                    write(False)
        kinds = [k for k in ("docker", "libvirt") if k in parts]
        if kinds:
            with tempfile.TemporaryDirectory(prefix="ccrp-bench-osl-") as tmp:
                try:
                    local_part(Path(tmp), args, kinds, result)
                except (Exception, SystemExit) as exc:
                    result["local_error"] = str(exc)[-1000:]
                    progress(f"docker/libvirt: FAILED: {exc}")
                finally:
                    write(False)
        if "aio" in parts:
            result["aio"]["at_rest_after"] = aio_status()
        result["load_after"] = load()
        os_clone = (result.get("openstack") or {}).get("clone")
        if os_clone:
            result["ratios"] = {f"ready_openstack_over_{k}": round(os_clone["ready"]["clone_s"] / result[k]["clone"]["ready"]["clone_s"], 1)
                                for k in kinds if k in result}
            result["ratios"] |= {f"wall_openstack_over_{k}": round(os_clone["ready"]["wall_s"] / result[k]["clone"]["ready"]["wall_s"], 1)
                                 for k in kinds if k in result}
        write(True)
    finally:
        if not result.get("complete"):
            result["load_after"] = load()
            write(False)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
