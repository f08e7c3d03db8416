"""Provisioning a fleet on the cloud fakes with 200 ms per API call (issue 5's benchmark).

For each cloud provider (aws on moto, openstack on the in-memory Nova/Neutron/Glance behind
requests-mock, gcp on autospecced compute_v1 clients), driven by the real provider code through
the contract harnesses (tests/contract/harness_<kind>.py):

  aws         moto in this process (mock_aws), one request at a time inside moto (its lock);
  aws-server  the same AwsProvider against `python -m moto.server`, a process of its own on
              127.0.0.1 (tests/contract/harness_aws_server.py: AWS_ENDPOINT_URL, no lock on the
              client side; werkzeug serves each connection on a thread of its own);
  aws-server-serial  the same, the server serving one request at a time (werkzeug unthreaded).

  bootstrap  from an empty fleet (network, security group / firewall, key pair, routes), then
             again as every later `fleet up` runs it (reuse: reads only);
  quotas     the fakes' quotas raised to N clones' worth (make_room); on openstack and gcp the
             check `fleet up` makes before creating (ccrp_cli/ops/quotas.py) is timed too, apart;
  fan-out    run_instance for every robot on the bounded pool of `fleet up` (reconcile._fan_out,
             provider.max_parallel workers), for 1, N/4, N/2 and N clones, each on a fresh fake:
             wall time, API calls (total and per clone), ratio to one clone, and that every robot
             ends up with exactly one instance; N once more with no latency, to show what the
             fake itself costs in CPU on this host.
  CPU        seconds of CPU during the fan-out, of this process (ccrp, the SDK, and the fakes that
             run in it) and of the moto server's process for the aws-server variants, which also
             count the server's responses with a 5xx status (harness_aws_server.py says which
             ccrp retries; a retry is counted as a call) and keep its request log's statuses.

  --entry gateway  the fleet behind an entry gateway (provider.entry: gateway): the gateway's
             instance made first (timed apart), then the clones, which take no public address;
             make_room leaves the fakes' address quotas at a new account's defaults (AWS 5 Elastic
             IPs, GCE 8 addresses, OpenStack 50 floating IPs), so 100 clones prove one address does.

Targets: wall(N) within 10x of wall(1) (4x behind a gateway, issue 42's goal); calls per clone flat
in N (no call count worse than linear in the fleet size). Clone specs (rendered user-data) are built before the clock starts:
they are local work, not API calls. The delay is injected by each harness before a call reaches
the fake, outside any fake lock, so concurrent calls overlap as on a real cloud.

Run: .venv/bin/python bench/provision_clouds.py [--clones 100] [--delay 0.2] [--providers aws,aws-server,openstack,gcp]
     [--entry per-clone|gateway]
Writes bench/results/provision_clouds.json and .png (provision_clouds_gateway.* with --entry gateway).
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib
import json
import os
import platform
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # the harnesses live in tests/contract

from ccrp_cli.ops import quotas  # noqa: E402
from ccrp_cli.ops.clones import CloneResult  # noqa: E402
from ccrp_cli.loader import inventory_model  # noqa: E402
from ccrp_cli.ops.reconcile import _fan_out  # noqa: E402
from tests.contract.specs import clone_spec  # noqa: E402

RESULTS = ROOT / "bench" / "results"
PROVIDERS = ["aws", "aws-server", "openstack", "gcp"]
# kind -> (harness module in tests/contract, make_harness keywords); otherwise harness_<kind>.
HARNESSES = {"aws-server": ("harness_aws_server", {}),
             "aws-server-serial": ("harness_aws_server", {"threaded": False})}
TARGETS = {"per-clone": 10, "gateway": 4}  # wall(N) / wall(1)
ADDRESS_QUOTAS = ("max_fips", "address_quota", "in_use_address_quota")


def progress(msg: str) -> None:
    print(f"bench: {msg}", file=sys.stderr, flush=True)


def fleet_specs(harness, n: int) -> dict:
    """CloneSpecs of robot1..robotN: the harness's inventory (fleet "ct") with N robots, the
    harness's own base image, user-data rendered as clones.ensure_clone renders it."""
    data = harness.provider.inv.model_dump(mode="json")
    data["robots"] = [{"name": f"robot{i}", "exports": [f"/robot{i}/odom"]} for i in range(1, n + 1)]
    inv = inventory_model().model_validate(data)  # the provider section checked against the registry
    image = harness.spec("robot1", 1).image
    return {f"robot{i}": clone_spec(inv, f"robot{i}", i, image) for i in range(1, n + 1)}


def make_room(harness, n: int, entry: str = "per-clone") -> None:
    """The fakes enforce quotas as small as a new project's (OpenStack 100 instances, 200 cores,
    400 GB of RAM, 50 floating IPs; GCE 24 vCPUs, 8 reserved and 8 in-use external addresses):
    give the project N clones' worth, as an operator would ask the cloud for before a fleet of N.
    moto enforces none of the limits it reports. Behind a gateway the address quotas stay as they are."""
    fake = getattr(harness, "fake", None)
    n += entry == "gateway"  # the gateway is an instance too
    for attr, per_clone in (("max_instances", 1), ("max_cores", 2), ("max_ram", 4096), ("max_fips", 1),  # m1.small
                            ("cpu_quota", 4), ("address_quota", 1), ("in_use_address_quota", 1)):
        if hasattr(fake, attr) and not (entry == "gateway" and attr in ADDRESS_QUOTAS):
            setattr(fake, attr, max(getattr(fake, attr), per_clone * n))


# Fakes whose quotas make_room raises: there the benchmark also times the check `fleet up` makes
# before creating (ccrp_cli/ops/quotas.py). moto's limits are fixed (5 Elastic IPs), so not on aws.
QUOTA_CHECKED = ("openstack", "gcp")


def fake_cpu(harness) -> float | None:
    """CPU seconds used so far by a fake in a process of its own (None: the fake is in this one)."""
    return harness.fake_cpu() if hasattr(harness, "fake_cpu") else None


def timed(harness, fn) -> tuple[float, Counter, object]:
    before = harness.api_calls()
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, harness.api_calls() - before, out


def server_errors(harness) -> dict | None:
    errors = getattr(harness, "server_errors", None)
    return None if errors is None else dict(sorted(errors.items()))


def gateway_spec(provider, spec):
    """The entry gateway's spec as ops/gateway.ensure makes it, from a clone's (its user-data aside:
    what the gateway runs is not what is timed here)."""
    from ccrp_cli.models.addressing import gateway_ip
    from ccrp_cli.providers.base import GATEWAY, GATEWAY_ROLE

    return spec.model_copy(update={"robot": GATEWAY, "role": GATEWAY_ROLE, "instance_id": f"{provider.fleet}-gateway",
                                   "common_ip": str(gateway_ip(provider.inv)), "vpn_subnet": None})


def run(kind: str, n: int, delay: float, entry: str = "per-clone") -> dict:
    """One fresh fake: bootstrap from empty, bootstrap again, (the gateway,) then N clones on the
    fan-out pool."""
    module, kwargs = HARNESSES.get(kind, (f"harness_{kind}", {}))
    mod = importlib.import_module(f"tests.contract.{module}")
    with tempfile.TemporaryDirectory() as tmp, mod.make_harness(Path(tmp), **kwargs) as h:
        make_room(h, n, entry)
        specs = fleet_specs(h, n)
        h.provider.teardown()  # the harness bootstrapped without latency: start from no network
        provider = h.provider
        if entry != "per-clone":
            inv = provider.inv
            provider = h.new_provider(inv.model_copy(update={"provider": inv.provider.model_copy(update={"entry": entry})}),
                                      Path(tmp) / f"{entry}-store")
        h.delay(delay)
        boot_s, boot_calls, _ = timed(h, provider.bootstrap)
        reuse_s, reuse_calls, _ = timed(h, provider.bootstrap)
        quota = None
        if kind in QUOTA_CHECKED:  # refused (QuotaError) if make_room left a quota short
            quota_s, quota_calls, uses = timed(h, lambda: quotas.check(provider, list(specs), progress))
            quota = {"wall_s": round(quota_s, 2), "calls": sum(quota_calls.values()),
                     "quotas": {u.quota.name: [u.quota.limit, u.quota.used, u.need] for u in uses}}
        gateway = None
        if entry == "gateway":
            gateway_s, gateway_calls, record = timed(h, lambda: provider.run_instance(gateway_spec(provider, specs["robot1"])))
            gateway = {"wall_s": round(gateway_s, 2), "calls": sum(gateway_calls.values()), "public_ip": record.public_ip}
        errors_before = server_errors(h) or {}
        cpu0, fake0 = time.process_time(), fake_cpu(h)
        wall, calls, results = timed(h, lambda: _fan_out(
            lambda r: provider.run_instance(specs[r]), list(specs), progress, provider))
        cpu, fake = time.process_time() - cpu0, fake_cpu(h)
        errors = server_errors(h)
        if errors is not None:
            errors = {k: v - errors_before.get(k, 0) for k, v in errors.items() if v - errors_before.get(k, 0)}
        h.delay(0)  # checks below read the fake, not the benchmark
        failed = {r.robot: r.detail for r in results if isinstance(r, CloneResult)}
        instances = Counter(h.instances_for(r) for r in specs)
        server = getattr(h, "server", None)  # the aws-server variants: every response in its log
        statuses = None if server is None else dict(sorted(server.status_counts().items()))
        total = sum(calls.values())
        public = sorted({r.public_ip for r in results if not isinstance(r, CloneResult) and r.public_ip})
        return {
            "clones": n,
            "workers": min(provider.max_parallel, n),
            # Public addresses the clones hold (none behind a gateway) and the gateway's making.
            "clone_public_ips": len(public),
            "gateway": gateway,
            "wall_s": round(wall, 2),
            "calls": total,
            "calls_per_clone": round(total / n, 2),
            "calls_by_operation": dict(sorted(calls.items(), key=str)),
            # CPU seconds during the fan-out: this process (all threads), the fake's own process.
            "cpu_s": round(cpu, 2),
            "fake_process_cpu_s": None if fake is None else round(fake - fake0, 2),
            "server_5xx": errors,
            "server_log_statuses": statuses,
            "failed": failed,
            "exactly_one_instance": instances == Counter({1: n}),
            "instances_per_robot": {str(k): v for k, v in sorted(instances.items())},
            "bootstrap": {"wall_s": round(boot_s, 2), "calls": sum(boot_calls.values()),
                          "reuse_wall_s": round(reuse_s, 2), "reuse_calls": sum(reuse_calls.values())},
            # The quota check before the fan-out (not in wall_s): its time, calls and each quota's
            # [limit, used, what the N clones need].
            "quota_check": quota,
        }


def bench_provider(kind: str, n: int, delay: float, entry: str = "per-clone") -> dict:
    sizes = sorted({1, max(1, n // 4), max(1, n // 2), n})
    runs = {}
    for size in sizes:
        runs[size] = run(kind, size, delay, entry)
        r = runs[size]
        progress(f"{kind}: {size} clones in {r['wall_s']:.1f} s, {r['calls']} calls "
                 f"({r['calls_per_clone']}/clone), {len(r['failed'])} failed, one instance each: "
                 f"{r['exactly_one_instance']}, CPU {r['cpu_s']} s here, {r['fake_process_cpu_s']} s in the "
                 f"fake's process, 5xx: {r['server_5xx']}, quota check: {r['quota_check']}")
    # The same N with no injected latency: what the fake and the SDK cost in CPU on this host,
    # which a real cloud spends on its own servers instead.
    cpu = run(kind, n, 0.0, entry)
    progress(f"{kind}: {n} clones with no latency in {cpu['wall_s']:.1f} s, CPU {cpu['cpu_s']} s here, "
             f"{cpu['fake_process_cpu_s']} s in the fake's process, 5xx: {cpu['server_5xx']}")
    one = runs[1]["wall_s"]
    for r in runs.values():
        r["ratio_to_1"] = round(r["wall_s"] / one, 2)
    per_clone = [runs[s]["calls_per_clone"] for s in sizes]
    full = runs[n]
    return {
        "max_parallel": full["workers"] if n > 1 else None,
        "bootstrap": full["bootstrap"],
        "quota_check": full["quota_check"],
        "runs": {str(s): r for s, r in runs.items()},
        "no_latency": {k: cpu[k] for k in ("clones", "wall_s", "calls", "cpu_s", "fake_process_cpu_s",
                                            "server_5xx", "failed")},
        "ratio_n_to_1": full["ratio_to_1"],
        "within_target": full["ratio_to_1"] <= TARGETS[entry],
        # Linear (or better): no size costs more calls per clone than one clone alone (5% slack).
        # Per-fleet reads cached by the provider (flavor, image) make larger fleets cheaper per clone.
        "calls_linear": max(per_clone) <= 1.05 * per_clone[0],
        "all_ok": all(not r["failed"] and r["exactly_one_instance"] for r in [*runs.values(), cpu])
        and (entry != "gateway" or all(r["clone_public_ips"] == 0 for r in [*runs.values(), cpu])),
    }


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    for i, (kind, res) in enumerate(result["providers"].items()):
        color = f"C{i}"
        sizes = [int(s) for s in res["runs"]]
        walls = [res["runs"][str(s)]["wall_s"] for s in sizes]
        ax1.plot(sizes, walls, "o-", color=color, label=f"{kind} ({res['max_parallel']} workers)")
        target = TARGETS[result["entry"]]
        ax1.axhline(target * res["runs"]["1"]["wall_s"], color=color, ls="--", lw=1,
                    label=f"{kind}: {target}x one clone")
        ax2.plot(sizes, [res["runs"][str(s)]["calls_per_clone"] for s in sizes], "o-", color=color, label=kind)
    ax1.set_xlabel("clones")
    ax1.set_ylabel("wall time (s)")
    ax1.set_title(f"run_instance fan-out, {result['delay_s'] * 1000:.0f} ms per API call")
    ax1.set_ylim(bottom=0)
    ax1.legend(fontsize=7)
    ax2.set_xlabel("clones")
    ax2.set_ylabel("API calls per clone")
    ax2.set_title("API calls per clone (flat = linear in fleet size)")
    ax2.set_ylim(bottom=0)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clones", type=int, default=100)
    ap.add_argument("--delay", type=float, default=0.2, help="seconds added to every API call")
    ap.add_argument("--providers", default=",".join(PROVIDERS))
    ap.add_argument("--entry", choices=sorted(TARGETS), default="per-clone",
                    help="the fleet's provider.entry: gateway keeps the address quotas at their defaults")
    args = ap.parse_args()
    name = "provision_clouds" if args.entry == "per-clone" else f"provision_clouds_{args.entry}"
    RESULTS.mkdir(parents=True, exist_ok=True)
    result = {
        "benchmark": "provision_clouds",
        "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release()},
        "clones": args.clones,
        "delay_s": args.delay,
        "entry": args.entry,
        "target_ratio": TARGETS[args.entry],
        "providers": {kind: bench_provider(kind, args.clones, args.delay, args.entry) for kind in args.providers.split(",")},
    }
    (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(result, RESULTS / f"{name}.png")
    for kind, res in result["providers"].items():
        progress(f"{kind}: {args.clones} clones at {res['ratio_n_to_1']}x one clone "
                 f"(within {TARGETS[args.entry]}x: {res['within_target']}), calls linear: {res['calls_linear']}, "
                 f"all ok: {res['all_ok']}")
    if not all(r["all_ok"] for r in result["providers"].values()):
        raise SystemExit(f"some clones failed, were duplicated or hold a public address: see bench/results/{name}.json")


if __name__ == "__main__":
    main()
