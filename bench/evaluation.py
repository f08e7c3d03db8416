"""The thesis's evaluation on the Docker lab fleet, through the CLI, beside the thesis's figures.

For each distro of --distros, one after the other in the same run: a copy of the thesis lab
(inventories/lab.yaml for Noetic, inventories/lab-jazzy.yaml for Jazzy; own fleet name, CCRP_HOME
and free subnets) scaled to --robots clones, then
  rtt     `ccrp bench rtt` for nao1 with no emulated link, --link eu and --link us
  teleop  `ccrp bench teleop` for nao1 on the same three links
  qos     `ccrp bench qos --robots 1..N --task-ms 100,500 --model cbm,pbm --link eu`
and `fleet down`, even on failure. Writes bench/results/evaluation[-<distro>][-<tag>].json (no
distro suffix for Noetic, as before) and its plots _qos.png and _links.png; docs/evaluation.md
holds the tables. --tag keeps a shorter run from replacing a full one's records.

Run: .venv/bin/python bench/evaluation.py [--distros noetic,jazzy] [--robots 10] [--duration 10] [--samples 100] [--tag T]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"
LINKS = ("none", "eu", "us")
LABS = {"noetic": "lab.yaml", "jazzy": "lab-jazzy.yaml"}

# The thesis (CCRP, 2019), Appendix D: mean response time in ms for 1..10 robots sending at once.
THESIS_QOS = {
    ("cbm", 100): [152, 153, 153, 154, 153, 151, 154, 155, 153, 154],
    ("pbm", 100): [147, 162, 178, 180, 204, 223, 241, 264, 284, 301],
    ("cbm", 500): [551, 550, 553, 550, 555, 552, 558, 555, 553, 554],
    ("pbm", 500): [542, 620, 718, 821, 951, 1188, 1281, 1712, 1994, 2211],
}
# Fig 7.1 (RTT from the UK, Wireshark, 100 samples) and chapter 8 (teleoperation).
THESIS_RTT = {"eu": 50, "us": 180}
THESIS_TELEOP = {"command (Turtlebot)": 250, "command (NAO)": 273, "video 320x240 5 fps": 150}


def stem(distro: str, tag: str = "") -> str:
    """evaluation (Noetic's records keep their name), evaluation-jazzy; -<tag> after either."""
    return "evaluation" + ("" if distro == "noetic" else f"-{distro}") + (f"-{tag}" if tag else "")


class Lab:
    def __init__(self, tmp: Path, distro: str) -> None:
        sys.path.insert(0, str(ROOT))
        from tests.scenarios.backend import free_cidr

        inv = yaml.safe_load((ROOT / "inventories" / LABS[distro]).read_text())
        assert inv["ros"]["distro"] == distro, (LABS[distro], inv["ros"])
        inv["fleet"] = f"eval{os.getpid() % 10000}"
        inv["provider"]["public_cidr"] = free_cidr("172.27.0.0/16")
        inv["common"]["cidr"] = free_cidr("10.97.0.0/16")
        inv["vpn"]["pool"] = free_cidr("10.64.0.0/12", prefix=16)
        self.inv = tmp / "lab.yaml"
        self.inv.write_text(yaml.safe_dump(inv))
        self.env = {**os.environ, "CCRP_HOME": str(tmp / "home")}

    def ccrp(self, *args: str, timeout: float = 3600) -> str:
        argv = [sys.executable, "-m", "ccrp_cli", *args[:2], "-i", str(self.inv), *args[2:]]
        print("+ ccrp", " ".join(args), file=sys.stderr, flush=True)
        proc = subprocess.run(argv, env=self.env, stdout=subprocess.PIPE, text=True, timeout=timeout)
        if proc.returncode != 0:
            raise SystemExit(f"ccrp {' '.join(args)} failed with exit {proc.returncode}")
        return proc.stdout

    def json(self, *args: str) -> list:
        return json.loads(self.ccrp(*args, "--json"))


def run(args, distro: str) -> dict:
    result: dict = {"distro": distro, "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
                    "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
                    "command": " ".join(["bench/evaluation.py", *sys.argv[1:]]), "rtt": {}, "teleop": {}}
    with tempfile.TemporaryDirectory(prefix="ccrp-eval-") as tmp:
        lab = Lab(Path(tmp), distro)
        try:
            lab.ccrp("vpn", "init")
            lab.ccrp("snapshot", "build", "--if-missing")
            lab.ccrp("fleet", "up")
            if args.robots > 3 and not args.links_only:
                lab.ccrp("fleet", "scale", str(args.robots))
            lab.ccrp("robot", "sim", "--robot", "nao1", "--wait", "90")
            for link in LINKS:
                lab.ccrp("robot", "sim", "--robot", "nao1", "--link", link)
                result["rtt"][link] = lab.json("bench", "rtt", "--robot", "nao1", "--samples", str(args.samples))
                result["teleop"][link] = lab.json("bench", "teleop", "--robot", "nao1", "--duration", str(args.duration * 2))
            lab.ccrp("robot", "sim", "--robot", "nao1", "--link", "none")
            if args.links_only:  # the qos records of the previous run are kept
                previous = json.loads((RESULTS / f"{stem(distro, args.tag)}.json").read_text())
                result["qos"], result["qos_date"] = previous["qos"], previous.get("qos_date")
                return result
            result["qos_date"] = result["date"]
            t0 = time.monotonic()
            result["qos"] = lab.json("bench", "qos", "--robots", f"1..{args.robots}", "--task-ms", "100,500",
                                     "--model", "cbm,pbm", "--duration", str(args.duration), "--link", "eu")
            result["qos_seconds"] = round(time.monotonic() - t0, 1)
        finally:
            lab.ccrp("robot", "sim", "--robot", "nao1", "--stop")
            lab.ccrp("fleet", "down")
    return result


def flatness(rows: list[dict], model: str, task: float, key: str = "mean_ms") -> float:
    """(max - min) / min of the mean (or `key`) response time over robot counts, in %."""
    means = [r[key] for r in rows if r["model"] == model and r["task_ms"] == task]
    return round(100 * (max(means) - min(means)) / min(means), 1)


def plot(result: dict, name: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = result["qos"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, task in zip(axes, (100, 500)):
        for model, color in (("cbm", "tab:green"), ("pbm", "tab:red")):
            mine = sorted((r["robots"], r["mean_ms"]) for r in rows if r["model"] == model and r["task_ms"] == task)
            ax.plot([n for n, _ in mine], [m for _, m in mine], "o-", color=color, label=f"{model.upper()} ccrp (link eu)")
            thesis = THESIS_QOS[(model, task)][: len(mine)]
            ax.plot(range(1, len(thesis) + 1), thesis, "x--", color=color, alpha=0.6, label=f"{model.upper()} thesis (GCP)")
        ax.set_title(f"task {task} ms")
        ax.set_xlabel("robots sending at once")
        ax.set_ylabel("mean response time (ms)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Clone per robot (CBM) vs one shared server (PBM), {result['distro']}")
    fig.tight_layout()
    fig.savefig(RESULTS / f"{name}_qos.png", dpi=110)

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    width = 0.27
    for i, (probe, label) in enumerate((("public (no VPN)", "ICMP, no VPN"), ("VPN", "ICMP, VPN"), ("ros", "ROS topic, VPN"))):
        means = []
        for link in LINKS:
            means.append(next(r["mean_ms"] for r in result["rtt"][link]
                              if (r["probe"] == "ros topic" if probe == "ros" else (r["path"], r["probe"]) == (probe, "icmp"))))
        ax1.bar([x + (i - 1) * width for x in range(len(LINKS))], means, width, label=label)
    for link, ms in THESIS_RTT.items():
        ax1.axhline(ms, color="grey", ls=":", lw=1)
        ax1.text(-0.4, ms + 3, f"thesis {link} ≈ {ms} ms", fontsize=8, color="grey")
    ax1.set_xticks(range(len(LINKS)), [f"link {x}" for x in LINKS])
    ax1.set_ylabel("round trip, mean (ms)")
    ax1.set_title(f"RTT robot -> clone, {result['distro']}")
    ax1.legend(fontsize=8)
    for i, stream in enumerate(("command", "video")):
        means = [next(r for r in result["teleop"][link] if r["stream"].startswith(stream))["mean_ms"] for link in LINKS]
        ax2.bar([x + (i - 0.5) * width for x in range(len(LINKS))], means, width, label=stream)
    ax2.set_yscale("log")
    ax2.set_xticks(range(len(LINKS)), [f"link {x}" for x in LINKS])
    ax2.set_ylabel("one-way latency, mean (ms, log)")
    ax2.set_title("Teleoperation (thesis: command 250-273 ms, video 150 ms)")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(RESULTS / f"{name}_links.png", dpi=110)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--distros", default="noetic,jazzy", help="a lab fleet of each, one after the other")
    ap.add_argument("--robots", type=int, default=10)
    ap.add_argument("--duration", type=float, default=10, help="seconds per qos round (teleop: twice this)")
    ap.add_argument("--samples", type=int, default=100)
    ap.add_argument("--links-only", action="store_true", help="rtt and teleop only; keep the qos records of the last run")
    ap.add_argument("--tag", default="", help="written as evaluation[-DISTRO]-TAG.json: a short run beside a full one")
    args = ap.parse_args()
    distros = [d.strip() for d in args.distros.split(",") if d.strip()]
    if not distros or set(distros) - set(LABS):
        ap.error(f"--distros: from {', '.join(LABS)}")
    RESULTS.mkdir(exist_ok=True)
    for distro in distros:
        result = run(args, distro)
        result["flatness_pct"] = {f"{m}_{t}": flatness(result["qos"], m, t) for m in ("cbm", "pbm") for t in (100, 500)}
        result["flatness_p50_pct"] = {f"{m}_{t}": flatness(result["qos"], m, t, "p50_ms")
                                      for m in ("cbm", "pbm") for t in (100, 500)}
        result["thesis"] = {"qos": {f"{m}_{t}": v for (m, t), v in THESIS_QOS.items()}, "rtt": THESIS_RTT, "teleop": THESIS_TELEOP}
        name = stem(distro, args.tag)
        (RESULTS / f"{name}.json").write_text(json.dumps(result, indent=2) + "\n")
        plot(result, name)
        print(json.dumps({"distro": distro, **result["flatness_pct"]}), flush=True)


if __name__ == "__main__":
    main()
