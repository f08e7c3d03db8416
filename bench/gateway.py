"""What the entry gateway adds to a robot's tunnel (docs/benchmarks.md "Entry gateway"): the same robot,
clone and OpenVPN, dialled directly and through the gateway's rules, side by side in one run.

Three network namespaces on this machine: "robot", "gateway" and "clone" (as tests/e2e/test_entry_gateway.py
lays them out), plus a direct veth from robot to clone. The clone runs the OpenVPN server ccrp renders
for nao1 of inventories/lab.yaml; the robot's client dials either the clone's own address (per-clone)
or the gateway's address at nao1's port (render/gateway.py's rules loaded in the gateway namespace).
Rounds alternate the two paths. Per round: the time from the client's start to its tunnel up, and
ICMP round trips through the tunnel (robot -> clone's VPN address).

The relay between clones does not cross the gateway (the common network), so it is not measured here.

Run (root, openvpn and iptables installed): .venv/bin/python bench/gateway.py [--rounds 5] [--pings 200]
Writes bench/results/gateway.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ccrp_cli.models.addressing import entry_port, gateway_ip  # noqa: E402
from ccrp_cli.render import gateway  # noqa: E402
from ccrp_cli.render.bundles import edge_bundle, write_bundle  # noqa: E402
from tests.e2e.vpnlab import COMPLETED, PINGS, OpenVPNProcess, build_fleet, serve_clone, sh, wait_for  # noqa: E402

RESULTS = ROOT / "bench" / "results"
NS = {p: f"ccrp-bench-{p}-{os.getpid()}" for p in ("robot", "gateway", "clone")}
GATEWAY_PUBLIC, ROBOT_PUBLIC = "198.51.100.1/24", "198.51.100.2/24"
CLONE_DIRECT, ROBOT_DIRECT = "192.0.2.1/24", "192.0.2.2/24"

def ns(place: str, *argv: str, check: bool = True):
    return sh("ip", "netns", "exec", NS[place], *argv, check=check)


def lay_out(lab) -> None:
    inv = lab.fleet.inventory
    for name in NS.values():
        sh("ip", "netns", "add", name)
        sh("ip", "-n", name, "link", "set", "lo", "up")
    links = (("robot", "pub", "gateway", "pub"), ("clone", "common", "gateway", "common"), ("robot", "direct", "clone", "direct"))
    for a, dev_a, b, dev_b in links:
        sh("ip", "-n", NS[a], "link", "add", dev_a, "type", "veth", "peer", "name", dev_b, "netns", NS[b])
    common = inv.common.cidr.prefixlen
    for place, dev, addr in (("robot", "pub", ROBOT_PUBLIC), ("gateway", "pub", GATEWAY_PUBLIC),
                             ("gateway", "common", f"{gateway_ip(inv)}/{common}"),
                             ("clone", "common", f"{lab.views['nao1'].addr.common_ip}/{common}"),
                             ("robot", "direct", ROBOT_DIRECT), ("clone", "direct", CLONE_DIRECT)):
        sh("ip", "-n", NS[place], "addr", "add", addr, "dev", dev)
        sh("ip", "-n", NS[place], "link", "set", dev, "up")
    rules = Path(tempfile.mkstemp(prefix="ccrp-bench-gw-")[1])
    rules.write_text(gateway.rules(inv, gateway.entries(inv, [lab.views["nao1"].addr]), "203.0.113.0/24"))
    ns("gateway", "sysctl", "-q", "-w", "net.ipv4.ip_forward=1")
    sh("sh", "-c", 'ip netns exec "$1" iptables-restore < "$2"', "-", NS["gateway"], str(rules))
    rules.unlink()


def one(lab, tmp: Path, remote: str, pings: int) -> dict:
    bundle = write_bundle(tmp / f"edge-{time.monotonic_ns()}", edge_bundle(lab.views["nao1"], lab.creds["nao1"], remote),
                          {"kind": "edge", "fleet": lab.fleet.name, "robot": "nao1"})
    t0 = time.monotonic()
    client = OpenVPNProcess.start(NS["robot"], tmp / f"client-{time.monotonic_ns()}.log", "--config",
                                  str(bundle / "robot.ovpn"), "--auth-user-pass", str(bundle / "vpn-credentials"))
    try:
        if not wait_for(lambda: COMPLETED in client.text(), 30, interval=0.02):
            raise RuntimeError(f"no tunnel through {remote}:\n{client.text()[-2000:]}")
        up = time.monotonic() - t0
        rtts = json.loads(ns("robot", sys.executable, "-c", PINGS, str(lab.views["nao1"].addr.clone_vpn_ip), str(pings)).stdout)
    finally:
        client.stop()
    time.sleep(1)  # the server lets the session go before the next round's client of the same robot
    return {"tunnel_up_s": round(up, 3), "answered": len(rtts), "rtt_ms": rtts}


def summary(rounds: list[dict]) -> dict:
    rtts = sorted(r for x in rounds for r in x["rtt_ms"])
    q = statistics.quantiles(rtts, n=100)
    return {"tunnel_up_s_median": round(statistics.median(x["tunnel_up_s"] for x in rounds), 3),
            "rtt_ms_p50": round(q[49], 3), "rtt_ms_p95": round(q[94], 3), "answered": len(rtts)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--pings", type=int, default=200)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="ccrp-bench-gateway-"))
    lab = build_fleet(ROOT / "inventories" / "lab.yaml", tmp / "home", ("nao1",))
    inv = lab.fleet.inventory
    paths = {"direct (per-clone)": CLONE_DIRECT.split("/")[0],
             "through the gateway": f"{GATEWAY_PUBLIC.split('/')[0]}:{entry_port(inv, lab.views['nao1'].addr.index)}"}
    rounds: dict[str, list[dict]] = {p: [] for p in paths}
    try:
        lay_out(lab)
        with serve_clone(NS["clone"], lab.views["nao1"], lab.creds["nao1"], tmp / "server.log"):
            for k in range(args.rounds):
                for name, remote in (paths.items() if k % 2 == 0 else reversed(paths.items())):
                    rounds[name].append(one(lab, tmp, remote, args.pings))
                    print(f"round {k + 1} {name}: tunnel up in {rounds[name][-1]['tunnel_up_s']} s", file=sys.stderr)
    finally:
        for name in NS.values():
            sh("ip", "netns", "delete", name, check=False)
    found = {name: summary(r) for name, r in rounds.items()}
    direct, via = found["direct (per-clone)"], found["through the gateway"]
    result = {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "rounds": args.rounds, "pings_per_round": args.pings, "paths": found,
        "ratio_rtt_p50": round(via["rtt_ms_p50"] / direct["rtt_ms_p50"], 2),
        "added_rtt_ms_p50": round(via["rtt_ms_p50"] - direct["rtt_ms_p50"], 3),
        "ratio_tunnel_up": round(via["tunnel_up_s_median"] / direct["tunnel_up_s_median"], 2),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "gateway.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "date"}, indent=2))


if __name__ == "__main__":
    main()
