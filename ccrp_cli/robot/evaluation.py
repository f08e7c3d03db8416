"""The thesis's evaluation as commands (`ccrp bench rtt|qos|teleop`), run between simulated robots
on this host and their clones on any provider.

Both ends run templates/bench/ccrp-bench (copied at each run); ccrp starts its roles, collects the
JSON they print, and leaves nothing behind: units stopped, simulated robots it started removed.
"""

from __future__ import annotations

import statistics
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TYPE_CHECKING, Callable, Iterator

from ..errors import CcrpError, InputError, shown
from ..fleet import Fleet
from ..models.layout import CCRP_LIB
from .simulated import Sims, run_unit

if TYPE_CHECKING:
    from ..providers.base import Lifecycle, Reaches

Progress = Callable[[str], None]
AGENT = f"{CCRP_LIB}/ccrp-bench"
SERVE_UNIT, WORKER_UNIT = "ccrp-bench-serve", "ccrp-bench-worker"
WORKER_PORT = 7460
# Runs the agent in the ROS environment of the machine (robot or clone). A constant: names and
# numbers reach the agent as separate arguments, never through the shell.
# A ROS 2 machine's setup.sh puts the wheels' venv (rclpy, OpenCV) on Debian's python3 path.
ROS_PRELUDE = ['/bin/sh', '-c', 'set -a; . /etc/ccrp/ros.env; set +a; '
               'if [ -f "/opt/ros/$ROS_DISTRO/setup.sh" ]; then . "/opt/ros/$ROS_DISTRO/setup.sh"; fi; exec "$@"']
IN_ROS = [*ROS_PRELUDE, 'ccrp-bench', '/usr/bin/python3', AGENT]


def summary(samples: list[float]) -> dict:
    """mean, p50, p95 and max of samples in ms (None each when there are none)."""
    if not samples:
        return {"mean_ms": None, "p50_ms": None, "p95_ms": None, "max_ms": None, "samples": 0}
    xs = sorted(samples)
    p95 = xs[min(len(xs) - 1, round(0.95 * (len(xs) - 1)))]
    return {"mean_ms": round(statistics.fmean(xs), 2), "p50_ms": round(statistics.median(xs), 2),
            "p95_ms": round(p95, 2), "max_ms": round(xs[-1], 2), "samples": len(xs)}


def parse_counts(text: str) -> list[int]:
    """`1..10`, `1,2,5` or `4`: robot counts, ascending."""
    try:
        if ".." in text:
            lo, hi = (int(x) for x in text.split("..", 1))
            counts = list(range(lo, hi + 1))
        else:
            counts = sorted({int(x) for x in text.split(",")})
    except ValueError:
        raise InputError(f"--robots {shown(text)} is not N, A..B or A,B,C", hint="e.g. --robots 1..10") from None
    if not counts or counts[0] < 1 or counts[-1] > 100:
        raise InputError(f"--robots {shown(text)}: counts from 1 to 100")
    return counts


def parse_list(text: str, allowed: tuple[str, ...] | None, what: str) -> list:
    items = [x.strip() for x in text.split(",") if x.strip()]
    if allowed is not None:
        bad = [x for x in items if x not in allowed]
        if bad or not items:
            raise InputError(f"{what} {shown(text)}: choose from {', '.join(allowed)}")
        return items
    try:
        values = [float(x) for x in items]
    except ValueError:
        values = []
    if not values or any(not 0 <= v <= 60_000 for v in values):
        raise InputError(f"{what} {shown(text)}: milliseconds from 0 to 60000, comma-separated")
    return values


class Bench:
    """The two ends of each robot taking part: its clone and its simulated robot."""

    def __init__(self, fleet: Fleet, progress: Progress = lambda m: None) -> None:
        self.fleet, self.progress = fleet, progress
        self.sims = Sims(fleet)
        self.clones = self.sims.clones
        self.state = fleet.store.load_state()
        self.plan = fleet.plan(self.state)
        self.started: list[str] = []  # simulated robots this run started: removed at the end
        self.relink: dict[str, object] = {}  # robots whose link this run changed: their own link back

    def prepare(self, robots: list[str]) -> None:
        """Each robot has a clone, a running simulated robot (started here if needed) and the
        agent on both ends."""
        from ..render.files import BundleFile
        from ..templates import static

        clones = self.clones.query()
        for robot in robots:
            self.fleet.robot(self.state, robot)
            if robot not in clones:
                raise InputError(f"robot {robot!r} has no clone", hint=f"ccrp clone create -i INVENTORY --robot {robot}")
        for robot in robots:
            if not self.sims.running(robot):
                self.progress(f"starting simulated robot {robot!r} for the bench (removed afterwards)")
                self.started.append(robot)
                self.sims.start(robot, wait=120, progress=self.progress)
        agent = [BundleFile("ccrp-bench", static("bench/ccrp-bench"), 0o755, AGENT)]
        for robot in robots:
            self.sims.push(robot, agent)
            self.clones.transport.push_files(robot, agent, restart=[])

    def on_robot(self, robot: str, args: list[str], timeout: float) -> dict:
        return _json(self.sims.exec(robot, [*IN_ROS, *args], timeout=timeout), f"simulated robot {robot!r}")

    def on_clone(self, robot: str, args: list[str], timeout: float) -> dict:
        return _json(self.clones.transport.exec(robot, [*IN_ROS, *args], timeout=timeout), f"the clone of {robot!r}")

    def background(self, robot: str, unit: str, args: list[str]) -> None:
        """Run an agent role as a transient unit on the clone (stopped by `stop_units`)."""
        run_unit(lambda argv: self.clones.transport.exec(robot, argv), unit, [*IN_ROS, *args], f"the clone of {robot!r}",
                 bench_unit_options(unit))

    def stop_units(self, robots: list[str], unit: str) -> None:
        _parallel(lambda r: self.clones.transport.exec(r, ["systemctl", "stop", unit]), robots)

    def shape(self, robots: list[str], link) -> None:
        """Every robot on `link` for this run."""
        for robot in robots:
            if robot not in self.started:
                self.relink.setdefault(robot, self.sims.link(robot))
        _parallel(lambda r: self.sims.set_link(r, link), robots)

    def cleanup(self) -> None:
        for robot, link in self.relink.items():
            if robot not in self.started:
                self.sims.set_link(robot, link)
        for robot in self.started:
            self.sims.stop(robot)
            self.progress(f"removed simulated robot {robot!r}")

    def link(self, robot: str) -> str:
        return str(self.sims.link(robot) or "none (this host's network)")


@contextmanager
def bench(fleet: Fleet, progress: Progress) -> Iterator[Bench]:
    b = Bench(fleet, progress)
    try:
        yield b
    finally:
        b.cleanup()


def bench_unit_options(unit: str) -> list[str]:
    """A bench role's transient unit: its ROS logs in a runtime directory of its own, gone with the
    unit (a unit has no HOME, without which rclpy cannot start: its logging needs a directory)."""
    run = f"/run/{unit}"
    return ["--collect", "--property", f"RuntimeDirectory={unit}", "--setenv", f"HOME={run}",
            "--setenv", f"ROS_HOME={run}", "--setenv", f"ROS_LOG_DIR={run}/log"]


def _json(result: tuple[int, str], where: str) -> dict:
    import json

    rc, out = result
    last = out.strip().splitlines()[-1] if out.strip() else ""
    if rc != 0 or not last.startswith("{"):
        raise CcrpError(f"the bench agent failed on {where} (exit {rc}): {out.strip()[-300:]}",
                        hint="is the robot connected? `ccrp status -i INVENTORY`")
    return json.loads(last)


def _parallel(fn: Callable, items: list) -> list:
    if not items:
        return []
    with ThreadPoolExecutor(max_workers=len(items)) as pool:
        return list(pool.map(fn, items))


def rtt(fleet: Fleet, robot: str, samples: int = 100, progress: Progress = lambda m: None) -> list[dict]:
    """Round trips from the robot to its clone: ICMP to the public address (no VPN), ICMP to the
    clone's VPN address (through the tunnel), and a ROS topic request/reply through the tunnel."""
    fleet.robot(fleet.store.load_state(), robot)  # an unknown robot is bad input, before any backend call
    with bench(fleet, progress) as b:
        b.prepare([robot])
        public, vpn_ip = b.sims.clone_address(robot), str(b.plan[robot].clone_vpn_ip)
        link, wait = b.link(robot), samples * 0.1 + 60
        rows = []
        for path, target in (("public (no VPN)", public), ("VPN", vpn_ip)):
            progress(f"{robot}: {samples} ICMP echoes to {target} ({path})")
            got = b.on_robot(robot, ["ping", target, "--count", str(samples)], wait)
            rows.append({"path": path, "probe": "icmp", "target": target, **summary(got["samples_ms"]), "lost": got["lost"]})
        progress(f"{robot}: {samples} ROS topic round trips through the VPN")
        b.background(robot, SERVE_UNIT, ["serve"])
        try:
            got = b.on_robot(robot, ["client", "--count", str(samples), "--period-ms", "100",
                                     "--duration", str(wait), "--timeout", "10"], wait + 40)
        finally:
            b.stop_units([robot], SERVE_UNIT)
        rows.append({"path": "VPN", "probe": "ros topic", "target": "/ccrp_bench/request -> /ccrp_bench/reply",
                     **summary(got["samples_ms"]), "lost": got["lost"]})
        return [{"robot": robot, "link": link, **row} for row in rows]


def qos(fleet: Fleet, counts: list[int], tasks_ms: list[float], models: list[str], duration: float = 10,
        link=None, progress: Progress = lambda m: None) -> list[dict]:
    """Response time of a fixed task as robots are added: clone-based (each robot's own clone does
    the task) vs proxy-based (one shared server does every robot's task, one at a time)."""
    members = [r.name for r in fleet.members(fleet.store.load_state())]
    if counts[-1] > len(members):
        raise InputError(f"--robots up to {counts[-1]} but fleet {fleet.name!r} has {len(members)} robots",
                         hint=f"ccrp fleet scale -i INVENTORY {counts[-1]}")
    robots = members[:counts[-1]]
    rows = []
    with bench(fleet, progress) as b:
        b.prepare(robots)
        if link is not None:
            b.shape(robots, link)
        shared = robots[0]  # the proxy's host: one clone serves every robot in the proxy-based runs
        shared_ip = str(b.plan[shared].common_ip)
        for model in models:
            for task in tasks_ms:
                for n in counts:
                    progress(f"{model} with {n} robot(s), task {task:g} ms: {duration:g} s of requests")
                    rows.append(_qos_round(b, model, robots[:n], task, duration, shared, shared_ip)
                                | {"link": link.spec if link else None})
    return rows


def _qos_round(b: Bench, model: str, robots: list[str], task: float, duration: float, shared: str, shared_ip: str) -> dict:
    try:
        if model == "pbm":
            b.background(shared, WORKER_UNIT, ["worker", "--port", str(WORKER_PORT), "--task-ms", f"{task:g}",
                                               "--allow", str(b.fleet.inventory.common.cidr)])
            serve = ["serve", "--worker", f"{shared_ip}:{WORKER_PORT}"]
        else:
            serve = ["serve", "--task-ms", f"{task:g}"]
        _parallel(lambda r: b.background(r, SERVE_UNIT, serve), robots)
        # Every robot starts at once, after its node found the clone's and warm-up requests drained.
        start_at = time.time() + 5 + 2 * len(robots) * task / 1000
        args = ["client", "--duration", f"{duration:g}", "--period-ms", f"{max(task, 1):g}", "--start-at", f"{start_at:.3f}"]
        results = _parallel(lambda r: b.on_robot(r, args, duration + 120), robots)
    finally:
        b.stop_units(robots, SERVE_UNIT)
        if model == "pbm":
            b.stop_units([shared], WORKER_UNIT)
    samples = [x for got in results for x in got["samples_ms"]]
    s = summary(samples)
    return {"model": model, "robots": len(robots), "task_ms": task, "mean_ms": s["mean_ms"], "p50_ms": s["p50_ms"],
            "p95_ms": s["p95_ms"], "samples": s["samples"], "lost": sum(got["lost"] for got in results)}


def teleop(fleet: Fleet, robot: str, duration: float = 20, progress: Progress = lambda m: None) -> list[dict]:
    """Teleoperation under the robot's current link: operator commands published on the clone to
    their arrival on the robot, and 320x240 camera frames at 5 fps from the robot to the clone."""
    fleet.robot(fleet.store.load_state(), robot)
    with bench(fleet, progress) as b:
        b.prepare([robot])
        link = b.link(robot)
        progress(f"{robot}: {duration:g} s of velocity commands (10 Hz) and camera frames (5 fps), link {link}")
        args = ["--duration", f"{duration:g}"]
        clone_side, robot_side = _parallel(
            lambda end: (b.on_clone if end == "clone" else b.on_robot)(robot, [f"teleop-{end}", *args], duration + 60),
            ["clone", "robot"])
        return [{"robot": robot, "link": link, "stream": "command (clone -> robot)", **summary(robot_side["command_ms"]),
                 "sent": clone_side["commands_sent"]},
                {"robot": robot, "link": link, "stream": "video 320x240 5 fps (robot -> clone)", **summary(clone_side["video_ms"]),
                 "sent": robot_side["frames_sent"]}]


# Teleoperation from ccrp (`ccrp robot teleop`, the dashboard's keys): one command per call, sent
# by the bench agent's `teleop-send` role on the clone, where an operator's node would publish it.
TOPIC_RE = r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*"
MAX_SPEED = 10.0  # m/s or rad/s: above this, a typo rather than a command
_pushed: set[tuple[str, str]] = set()  # (fleet, robot): the agent is on that clone (this process)
_operators: dict[tuple[str, str], float] = {}  # (fleet, robot) -> when this process started its teleop operator
TELEOP_UNIT, TELEOP_IDLE_S = "ccrp-teleop", 600.0
TELEOP_START_S = 15.0  # an operator not serving this long after its start has ended
# The operator's unit, as the camera agent's (camera.UNIT_OPTIONS): the `ros` user, not root; its
# socket (the agent's TELEOP_SOCKET, /run/ccrp-teleop/teleop.sock) and ROS logs in a 0700 runtime
# directory of that user, which teleop-send (as `ros` too, AS_ROS) and root reach, no other user.
TELEOP_UNIT_OPTIONS = ["--collect", "--description", "ccrp teleop operator (the dashboard's drive keys)",
                       "--property", "User=ros", "--property", "RuntimeDirectory=ccrp-teleop",
                       "--property", "RuntimeDirectoryMode=0700", "--property", "NoNewPrivileges=yes",
                       "--property", "ProtectSystem=full", "--property", "ProtectHome=yes",
                       "--property", "PrivateTmp=yes",
                       "--setenv", "HOME=/run/ccrp-teleop", "--setenv", "ROS_HOME=/run/ccrp-teleop",
                       "--setenv", "ROS_LOG_DIR=/run/ccrp-teleop/log"]
# A command without the operator (the CLI's, or the dashboard's while its operator starts) runs its
# node as the `ros` user too: runuser with the argv, no shell (its home is /var/lib/ros, its own).
AS_ROS = ["/usr/sbin/runuser", "-u", "ros", "--"]


def check_command(linear: float, angular: float, topic: str) -> None:
    import math
    import re

    for name, value in (("--linear", linear), ("--angular", angular)):
        if not math.isfinite(value) or abs(value) > MAX_SPEED:
            raise InputError(f"{name} {value!r} is out of range", hint=f"a velocity from -{MAX_SPEED:g} to {MAX_SPEED:g}")
    if len(topic) > 200 or not re.fullmatch(TOPIC_RE, topic):
        raise InputError(f"--topic {shown(topic)} is not a ROS topic name", hint="e.g. --topic cmd_vel or /mobile_base/cmd_vel")


def send_command(fleet: Fleet, provider: Lifecycle, robot: str, linear: float, angular: float, topic: str = "cmd_vel",
                 timeout: float = 5.0, keep: bool = False) -> dict:
    """Publish one geometry_msgs/Twist on the robot's clone and time its way to the robot: the
    round trip to the robot's acknowledgement, and clone publish -> robot receipt.

    With `keep` (the dashboard), an operator node is left running on the clone (TELEOP_UNIT, ends
    itself after TELEOP_IDLE_S without a command), so the next commands skip starting a ROS node."""
    import json

    from ..render.files import BundleFile
    from ..templates import static

    check_command(linear, angular, topic)
    fleet.robot(fleet.store.load_state(), robot)
    if robot not in provider.query():
        raise InputError(f"robot {robot!r} has no clone", hint=f"ccrp clone create -i INVENTORY --robot {robot}")
    argv = [*AS_ROS, *IN_ROS, "teleop-send", "--topic", topic, "--linear", repr(float(linear)), "--angular", repr(float(angular)),
            "--timeout", f"{timeout:g}"]
    key = (fleet.name, robot)
    t0 = time.perf_counter()
    for attempt in range(2):
        if key not in _pushed or attempt:
            provider.transport.push_files(robot, [BundleFile("ccrp-bench", static("bench/ccrp-bench"), 0o755, AGENT)], restart=[])
            _pushed.add(key)
        if keep and key not in _operators:
            run_unit(lambda a: provider.transport.exec(robot, a), TELEOP_UNIT,
                     [*IN_ROS, "teleop-operator", "--topic", topic, "--idle", f"{TELEOP_IDLE_S:g}"],
                     f"the clone of {robot!r}", TELEOP_UNIT_OPTIONS)
            _operators[key] = time.monotonic()
        rc, out = provider.transport.exec(robot, argv, timeout=timeout + 30)
        last = out.strip().splitlines()[-1] if out.strip() else ""
        if last.startswith("{"):
            break
        _operators.pop(key, None)
    if not last.startswith("{"):
        raise CcrpError(f"the teleop agent failed on the clone of {robot!r} (exit {rc}): {out.strip()[-300:]}",
                        hint="is the clone serving? `ccrp status -i INVENTORY`")
    got = json.loads(last)
    if got.get("via") != "operator" and time.monotonic() - _operators.get(key, -1e9) > TELEOP_START_S:
        _operators.pop(key, None)  # it ended (idle, the clone restarted): started again next time
    if "error" in got:
        raise CcrpError(f"robot {robot!r}: {got['error']}", hint="ccrp status -i INVENTORY (VPN, robot nodes)")
    return {"robot": robot, **got, "request_ms": round((time.perf_counter() - t0) * 1000, 1)}


def stop_operators(fleet: Fleet, provider: Reaches) -> list[str]:
    """Stop the teleop operators this process started on the fleet's clones (the dashboard ends)."""
    from .simulated import stop_unit

    robots = sorted(r for f, r in _operators if f == fleet.name)
    for robot in robots:
        try:
            stop_unit(lambda a: provider.transport.exec(robot, a), TELEOP_UNIT)  # noqa: B023 - called at once
        except CcrpError:
            pass  # its clone is gone or stopped: so is the operator
        _operators.pop((fleet.name, robot), None)
    return robots
