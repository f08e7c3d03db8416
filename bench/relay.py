"""Topic relay between clones on Docker (issue 4's benchmark), measured inside the clones.

  latency     a small message (std_msgs/Header, send time inside) published at 20 Hz on bot1's
              clone: received by a subscriber on the same master (direct) and, through the relay,
              on bot2's clone as /bot1/probe. p50/p95 of both, side by side in the same run.
  throughput  10 clones, each publishing a 320x240 rgb8 sensor_msgs/Image at 5 Hz and importing
              the next clone's (a ring: bot(k+1) sees /bot(k)/camera/image_raw): per stream,
              messages lost (sequence gaps) and p50/p95 latency (target: 0 loss, p95 < 50 ms).
              Where a loss happened: the importing agents' own gap counts (relay_gaps: between
              the agents, Zenoh) against the probes' (the rest: a DDS or ROS 1 hop in a clone).

All clones run on this host, so the senders' and receivers' clocks are the same clock. The
benchmark brings up its own fleet (own subnets and CCRP_HOME) and removes everything at the end.

The same for a ROS 2 Jazzy fleet (rclpy probes in the robots' domains, the relay's rclpy side),
one distro after the other in the same run.

Run: .venv/bin/python bench/relay.py [--clones 10] [--seconds 30] [--distros noetic,jazzy] [--host-rmem 4194304]
     [--ros2-spin spin_once|executor]
(--host-rmem: the host's receive-buffer sysctls during the run, as a VM clone's user-data sets them for
ROS 2; a container shares the host's kernel and cannot set its own)
Writes bench/results/relay.{json,png} (Noetic) and bench/results/relay-jazzy.{json,png}; with both
distros, relay-jazzy.json's `ratio_to_noetic` is Jazzy's figures over Noetic's of the same run.

  last hop    (--last-hop IMAGE, a ROS 2 clone image) the importing agent's publish to a subscriber
              on its clone, alone, in one container of IMAGE: serialized 320x240 images published
              as the agent publishes them (another user, the agent's Fast DDS profile from
              ccrp_cli/agent/relay_ros2.py) to the probe's rclpy subscriber as root; per variant,
              p50/p95 from the stamp and the datagrams the kernel dropped in full receive buffers.
              The subscriber spins an executor of its own (agent_reader_spin_once: the spin_once loop);
              --variants picks some, --host-rmem applies here too.
              Writes bench/results/relay-last-hop.json.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
import statistics
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from docker_fleet import RESULTS, Cli, cleanup_fleet  # noqa: E402

FLEET = "relaybench"

# Run in a clone as `python -c PROBE SPEC`: subscribes, publishes at a rate, prints what it saw.
# One head per ROS generation (its node, subscribers, publisher and clock), the same loop after it.
_PROBE_HEAD = r"""
import json, sys, threading, time
from sensor_msgs.msg import Image
from std_msgs.msg import Header
spec = json.loads(sys.argv[1])
seen = {t: {} for t in spec["subscribe"]}
cls = {"image": Image, "probe": Header}
def on(topic):
    def cb(msg):
        h = msg.header if hasattr(msg, "header") else msg
        seen[topic][int(h.frame_id)] = (time.time() - seconds(h.stamp)) * 1000.0
    return cb
"""
_ROS1 = r"""
import rospy
rospy.init_node("ccrp_bench", anonymous=True, disable_signals=True)
seconds, stamp = lambda t: t.to_sec(), rospy.Time.from_sec
subs = [rospy.Subscriber(t, cls[k], on(t), queue_size=100, tcp_nodelay=True) for t, k in spec["subscribe"].items()]
pub = rospy.Publisher(spec["publish"]["topic"], cls[spec["publish"]["kind"]], queue_size=100, tcp_nodelay=True) if spec.get("publish") else None
"""
# rclpy (ROS 2 clones, in the robot's domain through ros.env; run with the wheels' venv python).
# The relay's own participant is UDP only, so a probe run as root gets the imports it publishes.
_ROS2 = r"""
import rclpy
from builtin_interfaces.msg import Time
from rclpy.qos import QoSProfile
rclpy.init()
node = rclpy.create_node("ccrp_bench")
seconds = lambda t: t.sec + t.nanosec / 1e9
stamp = lambda now: Time(sec=int(now), nanosec=int((now % 1) * 1e9))
subs = [node.create_subscription(cls[k], t, on(t), QoSProfile(depth=100)) for t, k in spec["subscribe"].items()]
pub = node.create_publisher(cls[spec["publish"]["kind"]], spec["publish"]["topic"], QoSProfile(depth=100)) if spec.get("publish") else None
stop = threading.Event()
if spec.get("spin", "spin_once") == "spin_once":  # the global executor, one call per sample
    def spin():
        while not stop.is_set():
            rclpy.spin_once(node, timeout_sec=0.1)
    executor = None
else:  # an executor of its own spinning, as rclpy.spin(node) does
    from rclpy.executors import SingleThreadedExecutor
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spin = executor.spin
spinner = threading.Thread(target=spin)
spinner.start()
"""
_LOOP = r"""
time.sleep(spec["settle"])  # publishers, subscribers and relays find each other
data = bytes(320 * 240 * 3)
n, period, end = 0, 1.0 / (spec["publish"]["hz"] if pub else 1), time.time() + spec["seconds"]
nxt = time.time()
while time.time() < end:
    if pub:
        n += 1
        h = Header(frame_id=str(n), stamp=stamp(time.time()))
        pub.publish(Image(header=h, height=240, width=320, encoding="rgb8", step=960, data=data)
                    if spec["publish"]["kind"] == "image" else h)
    nxt += period
    time.sleep(max(0.0, nxt - time.time()))
time.sleep(2)  # in-flight messages
print(json.dumps({"sent": n, "seen": {t: {str(k): v for k, v in s.items()} for t, s in seen.items()}}))
"""
# rclpy aborts the process (exit 134) if the interpreter exits while a thread still spins.
_ROS2_END = r"""
stop.set()
if executor:
    executor.shutdown()
spinner.join()
rclpy.shutdown()
"""
PROBE, PROBE2 = _PROBE_HEAD + _ROS1 + _LOOP, _PROBE_HEAD + _ROS2 + _LOOP + _ROS2_END


def inventory(clones: int, distro: str) -> dict:
    robots = []
    for k in range(1, clones + 1):
        prev = f"bot{(k - 2) % clones + 1}"
        imports = {prev: ["/camera/image_raw"]}
        if k == 2:
            imports[prev].append("/probe")
        robots.append({"name": f"bot{k}", "exports": ["/camera/image_raw", "/probe"], "imports": imports})
    return {"fleet": FLEET, "provider": {"kind": "docker", "public_cidr": "172.27.0.0/24"}, "ros": {"distro": distro},
            "vpn": {"pool": "10.85.0.0/16"}, "common": {"cidr": "10.95.0.0/24"}, "robots": robots}


def probe(client, robot: str, spec: dict, distro: str) -> dict:
    c = client.containers.get(f"ccrp-{FLEET}-cri-{robot}")
    script, python = (PROBE, "python3") if distro == "noetic" else (PROBE2, f"/opt/ros/{distro}/bin/python")
    argv = ["bash", "-c", f'set -a; . /etc/ccrp/ros.env; set +a; exec {python} -c "$0" "$1"', script, json.dumps(spec)]
    res = c.exec_run(argv)
    out = res.output.decode(errors="replace")
    if res.exit_code != 0:
        raise SystemExit(f"probe on {robot} failed: {out[-800:]}")
    return json.loads(out.strip().splitlines()[-1])


# Read in a clone before and after the probes: its network namespace's UDP counters (RcvbufErrors:
# datagrams dropped because a socket's receive buffer was full) and the relay agent's CPU time.
_COUNTERS = ("cat /proc/net/snmp; pid=$(systemctl show -p MainPID --value ccrp-relay.service); "
             "echo relay $(cut -d' ' -f14,15 /proc/$pid/stat)")


def parse_counters(text: str, ticks: int) -> dict:
    """{udp_in, udp_rcvbuf_errors, udp_in_errors, relay_cpu_s} from _COUNTERS' output."""
    lines = text.splitlines()
    udp = [line.split()[1:] for line in lines if line.startswith("Udp:")]
    fields = dict(zip(udp[0], map(int, udp[1]))) if len(udp) >= 2 else {}
    relay = next((line.split()[1:] for line in lines if line.startswith("relay ")), [])
    cpu = sum(map(int, relay)) / ticks if len(relay) == 2 else None
    return {"udp_in": fields.get("InDatagrams"), "udp_rcvbuf_errors": fields.get("RcvbufErrors"),
            "udp_in_errors": fields.get("InErrors"), "relay_cpu_s": cpu}


def counters(client, robot: str) -> dict:
    c = client.containers.get(f"ccrp-{FLEET}-cri-{robot}")
    figures = parse_counters(c.exec_run(["sh", "-c", _COUNTERS]).output.decode(errors="replace"),
                             os.sysconf("SC_CLK_TCK"))
    # The container's CPU time (every process in it, the probes included), from the engine.
    figures["clone_cpu_s"] = c.stats(stream=False)["cpu_stats"]["cpu_usage"]["total_usage"] / 1e9
    return figures


def relay_gaps(client, robot: str) -> dict[str, int]:
    """Sequence numbers the importing agent of `robot`'s clone never got, per imported topic (its
    status file, written each second). A message a probe lost with no gap here was lost in a DDS
    (or ROS 1) hop inside a clone; one counted here, between the two agents (Zenoh)."""
    c = client.containers.get(f"ccrp-{FLEET}-cri-{robot}")
    res = c.exec_run(["cat", "/run/ccrp-relay/status.json"])
    try:
        imports = json.loads(res.output)["imports"] if res.exit_code == 0 else {}
    except (ValueError, KeyError):
        return {}
    return {topic: i.get("gaps", 0) for topic, i in imports.items()}


def counters_delta(before: dict, after: dict) -> dict:
    return {k: round(after[k] - before[k], 2) if after[k] is not None and before[k] is not None else None
            for k in before}


def stream_stats(sent: int, seen: dict[str, float], warmup: int, cooldown: int = 0) -> dict:
    """Loss over the messages sent after the warm-up ones and before the last `cooldown` ones (the
    probes start one `docker exec` after another, so a receiver may stop listening before a
    sender's last messages arrive); latency of those received."""
    window = range(warmup + 1, sent - cooldown + 1)
    got = [seen[str(i)] for i in window if str(i) in seen]
    missing = [i for i in range(warmup + 1, sent + 1) if str(i) not in seen]
    lat = sorted(got)
    q = lambda p: round(lat[min(len(lat) - 1, int(p * len(lat)))], 2) if lat else None  # noqa: E731
    return {"sent": len(window), "received": len(got), "lost": len(window) - len(got),
            "p50_ms": q(0.50), "p95_ms": q(0.95), "max_ms": round(lat[-1], 2) if lat else None,
            "missing_seq": missing[:20], "last_seq": sent}


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))
    lat = result["latency"]
    names = ["same master", "relay (clone to clone)"]
    for i, key in enumerate(("direct", "relay")):
        ax1.bar([i - 0.2], [lat[key]["p50_ms"]], 0.4, color="tab:blue", label="p50" if i == 0 else None)
        ax1.bar([i + 0.2], [lat[key]["p95_ms"]], 0.4, color="tab:orange", label="p95" if i == 0 else None)
    ax1.set_xticks([0, 1], names)
    ax1.set_ylabel("latency (ms)")
    ax1.set_title(f"{result['distro']}: small message (std_msgs/Header), 20 Hz")
    ax1.legend()
    streams = result["throughput"]["streams"]
    keys = sorted(streams, key=lambda s: int(s.split("/")[1][3:]))
    ax2.bar(range(len(keys)), [streams[k]["p95_ms"] for k in keys], color="tab:orange", label="p95")
    ax2.bar(range(len(keys)), [streams[k]["p50_ms"] for k in keys], color="tab:blue", label="p50")
    ax2.axhline(50, color="red", ls="--", label="target p95 50 ms")
    ax2.set_xticks(range(len(keys)), [k.split("/")[1] for k in keys], rotation=45)
    ax2.set_ylabel("latency (ms)")
    lost = sum(s["lost"] for s in streams.values())
    ax2.set_title(f"{len(keys)} image streams 320x240 rgb8 at 5 Hz (lost: {lost})")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


# --last-hop: run as root in the image (`python3 -c LAST_HOP DIR VARIANT`). DIR holds the profiles;
# the writer publishes bytes (rclpy publishes them raw, as the importing agent does).
_LAST_HOP_WRITER = r"""
import sys, time
import rclpy
from builtin_interfaces.msg import Time
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import Header
rclpy.init()
node = rclpy.create_node("last_hop_writer")
pub = node.create_publisher(Image, "/image", QoSProfile(depth=100))
end = time.time() + 10
while pub.get_subscription_count() < 1 and time.time() < end:
    time.sleep(0.05)
time.sleep(1)
data, hz, count = bytes(320 * 240 * 3), float(sys.argv[1]), int(sys.argv[2])
nxt = time.time()
for n in range(1, count + 1):
    now = time.time()
    h = Header(frame_id=str(n), stamp=Time(sec=int(now), nanosec=int((now % 1) * 1e9)))
    pub.publish(serialize_message(Image(header=h, height=240, width=320, encoding="rgb8", step=960, data=data)))
    nxt += 1.0 / hz
    time.sleep(max(0.0, nxt - time.time()))
time.sleep(1)
rclpy.shutdown()
"""
LAST_HOP = r"""
import json, os, subprocess, sys, time
d, variant, distro = sys.argv[1], sys.argv[2], sys.argv[3]
# agent_reader_spin_once: the agent's writer, the subscriber spinning as the probe did before
spin = "spin_once" if variant == "agent_reader_spin_once" else "executor"
if variant == "agent_reader_spin_once":
    variant = "agent"
hz, count = 10.0, int(sys.argv[4])
python = f"/opt/ros/{distro}/bin/python"
def udp():
    rows = [line.split() for line in open("/proc/net/snmp") if line.startswith("Udp:")]
    return dict(zip(rows[0][1:], map(int, rows[1][1:])))
os.makedirs("/tmp/log", mode=0o777, exist_ok=True)
os.chmod("/tmp/log", 0o777)
base = {**os.environ, "ROS_DOMAIN_ID": "42", "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp", "HOME": "/tmp",
        "ROS_LOG_DIR": "/tmp/log", "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
agent = {"FASTRTPS_DEFAULT_PROFILES_FILE": f"{d}/agent.xml", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SYSTEM_DEFAULT"}
writer_env, reader_env, demote = dict(base), dict(base), True
if variant == "shared_memory":  # the writer as the subscriber's user, as rmw sets it up: no profile
    demote = False
else:
    writer_env.update(agent, FASTRTPS_DEFAULT_PROFILES_FILE=f"{d}/{variant}.xml")
if variant == "subscriber_2mb":  # the subscriber's sockets as large as the agent's own
    reader_env.update(agent)
if variant == "agent_paced":  # its flow controller applies to asynchronous writers only
    writer_env["RMW_FASTRTPS_PUBLICATION_MODE"] = "ASYNCHRONOUS"
def nobody():
    os.setgid(65534)
    os.setuid(65534)
before = udp()
reader = subprocess.Popen([python, "-c", PROBE, json.dumps({"subscribe": {"/image": "image"}, "seconds": count / hz + 8, "settle": 0, "spin": spin})],
                          env=reader_env, stdout=subprocess.PIPE, text=True)
time.sleep(1.5)
writer = subprocess.Popen([python, "-c", WRITER, str(hz), str(count)], env=writer_env, preexec_fn=nobody if demote else None)
time.sleep(4)
ss = subprocess.run(["ss", "-uamn"], capture_output=True, text=True).stdout
writer.wait()
seen = json.loads(reader.communicate()[0].strip().splitlines()[-1])["seen"]["/image"]
after = udp()
print(json.dumps({"seen": seen, "rcvbuf_errors": after["RcvbufErrors"] - before["RcvbufErrors"],
                  "udp_in": after["InDatagrams"] - before["InDatagrams"],
                  "socket_rb": sorted({int(x.split("rb")[1].split(",")[0]) for x in ss.split() if x.startswith("skmem:")})}))
"""
LAST_HOP_VARIANTS = ("agent", "agent_reader_spin_once", "agent_writer_defaults", "agent_paced",
                     "shared_memory", "subscriber_2mb")
# Tried, not taken: the agent's writers paced to one 64 KB datagram per millisecond.
_PACED = """      <flow_controller_descriptor_list><flow_controller_descriptor><name>ccrp_paced</name>
        <max_bytes_per_period>65536</max_bytes_per_period><period_ms>1</period_ms>
      </flow_controller_descriptor></flow_controller_descriptor_list>
    </rtps>"""
_PACED_WRITER = "<publishMode><kind>ASYNCHRONOUS</kind><flow_controller_name>ccrp_paced</flow_controller_name></publishMode>"


def last_hop_profiles(profile: str) -> dict[str, str]:
    """The writer's Fast DDS profile per variant, from the agent's."""
    return {"agent": profile, "subscriber_2mb": profile,
            # The agent's profile before its writers answered NACKs at once.
            "agent_writer_defaults": re.sub(r"\s*<data_writer .*?</data_writer>", "", profile, flags=re.S),
            "agent_paced": profile.replace("    </rtps>", _PACED, 1).replace("<times>", f"<qos>{_PACED_WRITER}</qos><times>")}


def last_hop(image: str, distro: str, count: int, rounds: int, variants=LAST_HOP_VARIANTS) -> None:
    """The last hop alone (module docstring), each variant `rounds` times, interleaved."""
    import subprocess

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "ccrp_cli" / "agent"))
    import relay_ros2

    runs = {v: [] for v in variants}
    with tempfile.TemporaryDirectory() as tmp:
        os.chmod(tmp, 0o755)
        for name, text in last_hop_profiles(relay_ros2.fastdds_profile("")).items():
            (Path(tmp) / f"{name}.xml").write_text(text)
        script = LAST_HOP.replace("PROBE, json", f"{PROBE2!r}, json").replace("WRITER, str", f"{_LAST_HOP_WRITER!r}, str")
        for _ in range(rounds):
            for variant in variants:
                out = subprocess.run(["docker", "run", "--rm", "--name", f"relaybench-last-hop-{os.getpid()}",
                                      "-v", f"{tmp}:/bench:ro", "--entrypoint", "python3", image, "-c", script,
                                      "/bench", variant, distro, str(count)],
                                     capture_output=True, text=True, timeout=300)
                if out.returncode != 0:
                    raise SystemExit(f"last hop {variant} failed: {out.stderr[-800:]}")
                got = json.loads(out.stdout.strip().splitlines()[-1])
                stats = stream_stats(count, got.pop("seen"), 5)
                runs[variant].append({**{k: stats[k] for k in ("sent", "received", "lost", "p50_ms", "p95_ms", "max_ms")}, **got})
                print(f"last hop {variant}: {runs[variant][-1]}", file=sys.stderr)
    result = {"benchmark": "relay last hop", "image": image,
              "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
              "machine": {"cpus": os.cpu_count(), "kernel": platform.release(), "load": os.getloadavg(),
                          "rmem_default": int(Path(RMEM["default"]).read_text())},
              "images": count, "hz": 10, "runs": runs}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "relay-last-hop.json").write_text(json.dumps(result, indent=2) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clones", type=int, default=10)
    ap.add_argument("--seconds", type=float, default=30)
    ap.add_argument("--distros", default="noetic,jazzy", help="run the benchmark for each, one after the other")
    ap.add_argument("--last-hop", metavar="IMAGE", help="only the importing agent's last hop, in a ROS 2 clone image")
    ap.add_argument("--rounds", type=int, default=2, help="--last-hop: runs of each variant")
    ap.add_argument("--variants", default=",".join(LAST_HOP_VARIANTS), help="--last-hop: which, in this order")
    # Ten runs alternating the two (docs/ros2.md, Shared memory between the agent and your nodes) showed no
    # difference beyond the host's noise, so the probe stays as the earlier runs had it.
    ap.add_argument("--ros2-spin", choices=("spin_once", "executor"), default="spin_once",
                    help="how the ROS 2 probes take their samples: rclpy.spin_once called in a loop, or an "
                         "executor of their own spinning (as rclpy.spin does)")
    ap.add_argument("--host-rmem", type=int, metavar="BYTES",
                    help="the host's net.core.rmem_default and rmem_max during the run (put back after): what a "
                         "VM clone's user-data sets for ROS 2 (render/cloudinit.py ROS2_RMEM), which a container "
                         "cannot set for itself")
    args = ap.parse_args()
    summary = {}
    with host_rmem(args.host_rmem):
        if args.last_hop:
            distro = next(d for d in args.distros.split(",") if d != "noetic")  # the image's
            return last_hop(args.last_hop, distro, 105, args.rounds, args.variants.split(","))
        for distro in args.distros.split(","):
            summary[distro] = run(args, distro)
    if "noetic" in summary and len(summary) > 1:
        for distro, figures in summary.items():
            if distro != "noetic":
                figures["ratio_to_noetic"] = ratios(figures, summary["noetic"])
                path = RESULTS / f"relay-{distro}.json"
                result = json.loads(path.read_text())
                result["ratio_to_noetic"] = figures["ratio_to_noetic"]
                path.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(summary, indent=1))


RMEM = {"default": "/proc/sys/net/core/rmem_default", "max": "/proc/sys/net/core/rmem_max"}


@contextmanager
def host_rmem(size: int | None):
    """The host's receive-buffer sysctls at `size` meanwhile (None: as they are)."""
    if size is None:
        yield
        return
    saved = {k: Path(p).read_text() for k, p in RMEM.items()}
    try:
        for path in RMEM.values():
            Path(path).write_text(f"{size}\n")
        yield
    finally:
        for k, path in RMEM.items():
            Path(path).write_text(saved[k])


def ratios(figures: dict, noetic: dict) -> dict:
    """A distro's figures over Noetic's of the same run (issue 28's target: at most 2)."""
    r = lambda a, b: round(a / b, 2) if a is not None and b else None  # noqa: E731
    relay, relay1 = figures["latency"]["relay"], noetic["latency"]["relay"]
    return {"images_p95_median": r(figures["p95_ms_median"], noetic["p95_ms_median"]),
            "images_p95_worst": r(figures["p95_ms_worst"], noetic["p95_ms_worst"]),
            "images_p50_median": r(figures["p50_ms_median"], noetic["p50_ms_median"]),
            "small_relay_p50": r(relay["p50_ms"], relay1["p50_ms"]),
            "small_relay_p95": r(relay["p95_ms"], relay1["p95_ms"])}


def run(args, distro: str) -> dict:
    import docker

    client = docker.from_env(timeout=600)
    warmup_s = 3
    load_before = os.getloadavg()  # the host is shared: its load says how much the figures carry
    with tempfile.TemporaryDirectory() as tmp:
        home, inv = Path(tmp) / "home", Path(tmp) / "relay.yaml"
        inv.write_text(yaml.safe_dump(inventory(args.clones, distro), sort_keys=False))
        cli = Cli(home, inv)
        try:
            cli("vpn", "init")
            cli("snapshot", "build")
            wall, _ = cli("fleet", "up", "--json")
            print(f"bench: {args.clones} {distro} clones up in {wall:.1f} s", file=sys.stderr)
            robots = [f"bot{k}" for k in range(1, args.clones + 1)]
            specs = {}
            for k, robot in enumerate(robots, 1):
                nxt = f"bot{k % args.clones + 1}"  # its image goes to the next clone
                subs = {f"/bot{(k - 2) % args.clones + 1}/camera/image_raw": "image"}
                if robot == "bot1":
                    subs["/probe"] = "probe"  # direct: same master as the publisher below
                if robot == "bot2":
                    subs["/bot1/probe"] = "probe"  # through the relay
                specs[robot] = {"publish": {"topic": "/camera/image_raw", "kind": "image", "hz": 5},
                                "subscribe": subs, "seconds": args.seconds, "settle": 6, "next": nxt,
                                "spin": args.ros2_spin}
            # bot1 publishes the probe as well, from a second process so the image loop stays at 5 Hz.
            probe_spec = {"publish": {"topic": "/probe", "kind": "probe", "hz": 20}, "subscribe": {},
                          "seconds": args.seconds, "settle": 6, "spin": args.ros2_spin}
            with ThreadPoolExecutor(len(robots) + 1) as pool:
                before = dict(zip(robots, pool.map(lambda r: counters(client, r), robots)))
                futures = {r: pool.submit(probe, client, r, specs[r], distro) for r in robots}
                probe_sender = pool.submit(probe, client, "bot1", probe_spec, distro)
                out = {r: f.result() for r, f in futures.items()}
                sent_probe = probe_sender.result()["sent"]
                after = dict(zip(robots, pool.map(lambda r: counters(client, r), robots)))
                time.sleep(1.5)  # the agents write their status each second
                gaps = dict(zip(robots, pool.map(lambda r: relay_gaps(client, r), robots)))
        finally:
            try:
                cli("fleet", "down")
            finally:
                cleanup_fleet(FLEET)

    streams = {}
    for k, robot in enumerate(robots, 1):
        src = f"bot{(k - 2) % args.clones + 1}"
        topic = f"/{src}/camera/image_raw"
        streams[f"{robot}/{src}"] = stream_stats(out[src]["sent"], out[robot]["seen"][topic], warmup_s * 5, 5)
    result = {
        "benchmark": "relay",
        "distro": distro,
        "when": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "kernel": platform.release(),
                    "rmem_default": int(Path(RMEM["default"]).read_text()),
                    "load_before": [round(x, 2) for x in load_before],
                    "load_after": [round(x, 2) for x in os.getloadavg()]},
        "seconds": args.seconds,
        "ros2_spin": args.ros2_spin if distro != "noetic" else None,
        "clones_up_s": round(wall, 1),
        "latency": {
            "direct": stream_stats(sent_probe, out["bot1"]["seen"]["/probe"], warmup_s * 20, 20),
            "relay": stream_stats(sent_probe, out["bot2"]["seen"]["/bot1/probe"], warmup_s * 20, 20),
        },
        "throughput": {"clones": args.clones, "image": "320x240 rgb8", "hz": 5, "streams": streams},
    }
    t = result["throughput"]
    t["lost_total"] = sum(s["lost"] for s in streams.values())
    t["p95_ms_worst"] = max(s["p95_ms"] or 0 for s in streams.values())
    t["p95_ms_median"] = statistics.median(s["p95_ms"] or 0 for s in streams.values())
    # While the probes ran (settle, seconds and their tail): what each clone's kernel dropped
    # in full UDP receive buffers (ROS 2's DDS hops; ROS 1's are TCP), and the CPU time spent.
    clones = {r: counters_delta(before[r], after[r]) for r in robots}
    total = lambda k: round(sum(c[k] for c in clones.values() if c[k] is not None), 2)  # noqa: E731
    result["clones"] = {"udp_rcvbuf_errors": total("udp_rcvbuf_errors"), "udp_in": total("udp_in"),
                        "relay_cpu_s": total("relay_cpu_s"), "clone_cpu_s": total("clone_cpu_s"),
                        "relay_gaps": sum(sum(g.values()) for g in gaps.values()),
                        "per_clone": clones, "relay_gaps_per_clone": gaps}
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = "relay" if distro == "noetic" else f"relay-{distro}"
    (RESULTS / f"{stem}.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(result, RESULTS / f"{stem}.png")
    return {"latency": result["latency"], "lost_total": t["lost_total"], "p95_ms_worst": t["p95_ms_worst"],
            "p95_ms_median": t["p95_ms_median"], "rmem_default": result["machine"]["rmem_default"],
            "p50_ms_median": statistics.median(s["p50_ms"] or 0 for s in streams.values()),
            "load": [result["machine"]["load_before"][0], result["machine"]["load_after"][0]],
            "clones": {k: v for k, v in result["clones"].items() if not k.endswith("per_clone")}}


if __name__ == "__main__":
    main()
