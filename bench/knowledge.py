"""Knowledge sync: time for an item added on one clone to be on every other clone sharing its
dataset, for N = 2, 5 and 10 clones (docs/services.md, Knowledge sync, Measured).

N knowledge agents (ccrp_cli/agent/knowledge.py, the code the clones run) in this process, each
with its own Zenoh session on loopback, mutual TLS with relay certificates from a throwaway
fleet's PKI (as on a fleet: one certificate per clone, partners admitted by CN), every agent
linked to every other. An item is added on clone 1 through its control socket; the time is taken
from that request's answer (the item stored on clone 1 and its event sent) to when the last
other clone's files/ has it. Loopback only: the common network's latency is not in it (the Docker
fleet's figure is in tests/e2e/test_docker_fleet.py's log).

Run: .venv/bin/python bench/knowledge.py [--samples 20] [--size 65536]
Writes bench/results/knowledge.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import secrets
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ccrp_cli.agent import knowledge as agent  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pki(home: Path, n: int):
    """A fleet's relay CA and one relay certificate per clone (ccrp's own PKI code)."""
    import yaml

    os.environ["CCRP_HOME"] = str(home / "home")
    from ccrp_cli.ops import vpn
    from ccrp_cli.fleet import Fleet

    data = yaml.safe_load((ROOT / "inventories" / "lab.yaml").read_text())
    data["fleet"] = "bench"
    data["robots"] = [{"name": f"c{i}"} for i in range(1, n + 1)]
    data.pop("template", None)
    inv = home / "bench.yaml"
    inv.write_text(yaml.safe_dump(data))
    fleet = Fleet.open(inv)
    vpn.init(fleet)
    for i in range(1, n + 1):
        fleet.pki.issue_relay(f"c{i}", "127.0.0.1", 30)
    return fleet


def run(n: int, samples: int, size: int, tmp: Path) -> dict:
    fleet = pki(tmp, n)
    names = [f"c{i}" for i in range(1, n + 1)]
    cns = fleet.pki.relay_cns()
    index = fleet.pki.load_index()
    ports = {r: free_port() for r in names}
    ids = {r: "c" + hashlib.sha256(r.encode()).hexdigest()[:23] for r in names}  # no leading 0 (Zenoh)
    agents = {}
    for r in names:
        c = fleet.pki.current_of(index, "relay", r)
        cfg = {"fleet": "bench", "robot": r, "id": ids[r], "listen": f"tls/127.0.0.1:{ports[r]}", "reconcile": 3600,
               "peers": {p: {"endpoint": f"tls/127.0.0.1:{ports[p]}", "id": ids[p], "cn": cns[p]}
                         for p in names if p != r},
               "datasets": {"faces": names},
               "tls": {"ca": str(fleet.pki.relay_ca_path), "cert": str(fleet.pki.root / c.cert_path),
                       "key": str(fleet.pki.root / c.key_path)},
               "root": str(tmp / r), "status": str(tmp / f"{r}.status")}
        agents[r] = agent.Agent(cfg)
    deadline = time.monotonic() + 30
    while not all(len(a.session.info.peers_zid()) == n - 1 for a in agents.values()):
        if time.monotonic() > deadline:
            raise SystemExit(f"{n} agents did not link within 30 s")
        time.sleep(0.05)
    first = agents["c1"]
    times = []
    for k in range(samples):
        data = secrets.token_bytes(size)
        name = f"item{k}.bin"
        reply = first.call(lambda: first.request({"op": "add", "dataset": "faces", "name": name}, data))
        t0 = time.monotonic()
        assert reply["ok"], reply
        paths = [tmp / r / "faces" / "files" / name for r in names[1:]]
        while not all(p.exists() for p in paths):
            if time.monotonic() - t0 > 30:
                raise SystemExit(f"item {k} not on every clone within 30 s")
            time.sleep(0.002)
        times.append((time.monotonic() - t0) * 1000)
    for a in agents.values():
        a.session.close()
    times.sort()
    return {"clones": n, "samples": samples, "size": size, "p50_ms": round(statistics.median(times), 1),
            "p95_ms": round(times[int(0.95 * (len(times) - 1))], 1), "max_ms": round(times[-1], 1)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", type=int, default=20)
    ap.add_argument("--size", type=int, default=64 << 10)
    args = ap.parse_args()
    rows = []
    for n in (2, 5, 10):
        with tempfile.TemporaryDirectory() as tmp:
            row = run(n, args.samples, args.size, Path(tmp))
        print(json.dumps(row), flush=True)
        rows.append(row)
    out = {"host": {"cpus": os.cpu_count(), "python": platform.python_version()}, "results": rows}
    (ROOT / "bench" / "results" / "knowledge.json").write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    threading.excepthook = lambda args: None  # the agents' daemon threads end with the process
    main()
