"""The harness of the end-to-end tests on Docker: a fleet of its own per module (`start_fleet`),
driven through the CLI in subprocesses, swept away by its labels whatever happens; probes run in
its containers; and what a failing test prints about the fleet (`diagnostics`). Fixtures built on it
are in conftest.py; this module holds no test."""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import string
import subprocess
import sys
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import docker
import pytest
import yaml

from tests.conftest import LAB, run_ccrp
from tests.inprocess_cli import run_ccrp_inprocess
from tests.scenarios.backend import free_cidr

def _docker_info() -> str | None:
    """None when the engine answers `docker info`, else why not."""
    if shutil.which("docker") is None:
        return "the docker CLI is not installed"
    try:
        proc = subprocess.run(["docker", "info", "--format", "{{.ServerVersion}}"], capture_output=True,
                              text=True, timeout=20)
    except subprocess.TimeoutExpired:
        return "`docker info` did not answer within 20 s"
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["?"])[-1]
        return f"`docker info` failed: {last}"
    return None


NO_DOCKER = _docker_info()

ROBOTS = ("nao1", "nao2", "turtlebot1")
FLEET_LABEL = "ccrp-fleet"
COMPLETED = "Initialization Sequence Completed"
CONNECT_TIMEOUT = 30.0   # a simulated robot's node registered on its clone's master
REVOKE_TIMEOUT = 10.0    # a revoked robot's live session ended (issue: within 10 s)
# Markers of private key material in text; a hit must also be a whole PEM block with a body
# (libraries and docs carry the bare header strings).
PEM_BLOCK = re.compile(
    rb"-----BEGIN ((?:[A-Z0-9]+ )*PRIVATE KEY|OpenVPN Static key V1)-----[\r\n]+"
    rb"(?:[A-Za-z0-9+/=:,\- ]*[\r\n]+){2,}-----END \1-----"
)
MARKERS = (b"PRIVATE KEY", b"OpenVPN Static key")


# -- the module's fleet ------------------------------------------------------------------------


@dataclass
class E2EFleet:
    name: str
    inventory: Path
    home: Path
    client: object  # docker.DockerClient
    tmp: Path
    log: list[str] = field(default_factory=list)

    # ccrp through its CLI, in a subprocess: real exit codes, real stderr.
    def run(self, *args: str, check: bool = False) -> subprocess.CompletedProcess:
        t0 = time.monotonic()
        proc = run_ccrp(*args, home=self.home)
        shown = " ".join(a if len(a) < 60 and "\n" not in a else "<...>" for a in args)
        self.log.append(f"ccrp {shown} -> {proc.returncode} in {time.monotonic() - t0:.1f}s")
        if check and proc.returncode != 0:
            pytest.fail(f"`ccrp {' '.join(args)}` exited {proc.returncode}:\n{proc.stderr[-3000:]}")
        return proc

    def inv(self, *args: str, check: bool = False) -> subprocess.CompletedProcess:
        """ccrp <args> -i <the module's inventory> (before a `--`, when there is one)"""
        cut = args.index("--") if "--" in args else len(args)
        return self.run(*args[:cut], "-i", str(self.inventory), *args[cut:], check=check)

    def json(self, *args: str) -> object:
        proc = self.inv(*args, "--json", check=True)
        try:
            return json.loads(proc.stdout)
        except ValueError:
            pytest.fail(f"`ccrp {' '.join(args)} --json` printed no JSON on stdout:\n{proc.stdout[:2000]}")

    @property
    def diagnostic_labels(self) -> list[str]:
        """What a failing test prints the containers of (conftest.py)."""
        return [f"{FLEET_LABEL}={self.name}"]

    def env(self) -> dict[str, str]:
        env = {**os.environ, "CCRP_HOME": str(self.home)}
        env.pop("CCRP_INVENTORY", None)
        return env

    # -- what Docker has, by the fleet's labels ----------------------------------------------
    def labelled(self, **labels: str) -> dict[str, str]:
        return {"label": [f"{FLEET_LABEL}={self.name}", *(f"ccrp-{k}={v}" for k, v in labels.items())]}

    def containers(self, **labels: str) -> list:
        return self.client.containers.list(ignore_removed=True, all=True, filters=self.labelled(**labels))

    def container(self, role: str, robot: str):
        found = self.containers(role=role, robot=robot)
        assert len(found) == 1, f"expected one {role} container of {robot}, found {[c.name for c in found]}"
        return found[0]

    def status(self) -> dict[str, dict]:
        """`ccrp status --json`, run in this process (tests/inprocess_cli.py): the same command and
        output, without a Python start on every poll of a wait (a `ccrp` process costs ~1.3 s of CPU,
        mostly imports, that the clones booting beside it need). The CLI's own `status` is proved
        by the tests that call `fleet.inv("status")`."""
        t0 = time.monotonic()
        code, out, err = run_ccrp_inprocess("status", "-i", str(self.inventory), "--json", home=self.home)
        self.log.append(f"ccrp status --json (in process) -> {code} in {time.monotonic() - t0:.1f}s")
        if code != 0:
            pytest.fail(f"`ccrp status --json` exited {code}:\n{err[-3000:]}")
        try:
            return {row["robot"]: row for row in json.loads(out)}
        except ValueError:
            pytest.fail(f"`ccrp status --json` printed no JSON on stdout:\n{out[:2000]}")

    def snapshot_image(self) -> str:
        state = json.loads((self.home / self.name / "state.json").read_text())
        return state["snapshot"]["image"]

    def plan(self) -> dict[str, dict]:
        return {r["name"]: r for r in self.json("fleet", "validate")["robots"]}

    def secret_needles(self) -> dict[bytes, str]:
        """Fragments of every secret in the fleet's PKI store: key bodies, tls-crypt keys, passwords."""
        pki = self.home / self.name / "pki"
        needles: dict[bytes, str] = {}
        for path in sorted((pki / "private").glob("*.key")) + sorted((pki / "tls-crypt").glob("*.key")):
            body = [ln.strip() for ln in path.read_text().splitlines()
                    if ln.strip() and not ln.startswith(("-----", "#"))]
            for line in body[:2]:  # random from the first line on (a P-256 key has 16 random chars there)
                needles[line.encode()] = f"pki/{path.parent.name}/{path.name}"
        for path in sorted((pki / "passwords").glob("*.txt")):
            needles[path.read_text().strip().encode()] = f"pki/passwords/{path.name}"
        assert needles, f"no secrets found under {pki}"
        return needles


def free_subnets() -> tuple[str, str, str]:
    """public, common and VPN pool subnets that no Docker network or route of this host overlaps."""
    return free_cidr("172.31.0.0/16"), free_cidr("10.91.0.0/16"), free_cidr("10.84.0.0/14", prefix=16)


def sweep(client, fleet: str) -> list[str]:
    """Remove everything labelled with `fleet` (and containers of its images). Returns what is left."""
    by_label = {"label": [f"{FLEET_LABEL}={fleet}"]}
    problems = []

    def attempt(what: str, fn: Callable[[], object]) -> None:
        try:
            fn()
        except docker.errors.NotFound:
            pass
        except Exception as exc:  # noqa: BLE001 - keep sweeping; report at the end
            problems.append(f"{what}: {exc}")

    images = client.images.list(filters=by_label)
    containers = {c.id: c for c in client.containers.list(ignore_removed=True, all=True, filters=by_label)}
    for image in images:
        for c in client.containers.list(ignore_removed=True, all=True, filters={"ancestor": image.id}):
            containers[c.id] = c
    # Simulated power devices first: each holds its robot's power-line volume, which goes with the robot.
    for c in sorted(containers.values(), key=lambda c: c.labels.get("ccrp-role") != "power-sim"):
        attempt(f"container {c.name}", lambda c=c: c.remove(force=True, v=True))
    for v in client.volumes.list(filters=by_label):
        attempt(f"volume {v.name}", lambda v=v: v.remove(force=True))
    for n in client.networks.list(filters=by_label):
        attempt(f"network {n.name}", n.remove)
    for image in images:
        attempt(f"image {image.tags or image.id}", lambda i=image: client.images.remove(i.id, force=True))
    left = (
        [f"container {c.name}" for c in client.containers.list(ignore_removed=True, all=True, filters=by_label)]
        + [f"volume {v.name}" for v in client.volumes.list(filters=by_label)]
        + [f"network {n.name}" for n in client.networks.list(filters=by_label)]
        + [f"image {i.tags or i.id}" for i in client.images.list(filters=by_label)]
    )
    return problems + left


def example_inventory(example: Path, robots: tuple[str, ...]) -> Callable[[dict], None]:
    """start_fleet's `edit` for an example's inventory (examples/...yaml): the example with
    start_fleet's fleet name and networks, and `robots` alone."""
    def edit(data: dict) -> None:
        loaded = yaml.safe_load(example.read_text())
        keep = {k: data[k] for k in ("fleet", "provider", "vpn", "common")}
        data.clear()
        data.update(loaded)
        data.update(keep)
        data["robots"] = [r for r in loaded["robots"] if r["name"] in robots]

    return edit


def start_fleet(request, tmp_path_factory, prefix: str, edit: Callable[[dict], None] = lambda data: None,
                copy: dict[str, Path] | None = None) -> E2EFleet:
    """A fleet of its own from inventories/lab.yaml (`edit` changes the inventory), with its CA and
    snapshot; swept away when the requesting scope ends, even on failure. `copy` puts directories
    beside the inventory (a workspace its `software:` names, relative to it)."""
    client = docker.from_env(timeout=300)
    name = prefix + "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(6))
    public, common, pool = free_subnets()
    tmp = tmp_path_factory.mktemp(name)
    data = yaml.safe_load(LAB.read_text())
    data["fleet"] = name
    edit(data)
    data["provider"]["public_cidr"] = public
    data["common"]["cidr"] = common
    data["vpn"]["pool"] = pool
    for rel, source in (copy or {}).items():
        shutil.copytree(source, tmp / rel, ignore=shutil.ignore_patterns("build", "install", "log", "__pycache__"))
    inventory = tmp / "inventory.yaml"
    inventory.write_text(yaml.safe_dump(data, sort_keys=False))
    f = E2EFleet(name=name, inventory=inventory, home=tmp / "home", client=client, tmp=tmp)

    def teardown() -> None:
        crashed = abnormal_exits(client, f"{FLEET_LABEL}={name}")  # before fleet down takes the journals
        try:
            f.inv("fleet", "down")
        except Exception as exc:  # noqa: BLE001 - the sweep below still runs
            warnings.warn(f"ccrp fleet down of {name} failed: {exc}", stacklevel=1)
        left = sweep(client, name)
        if left:
            warnings.warn(f"e2e fleet {name}: could not remove {left}", stacklevel=1)
        sys.stderr.write("\n" + "\n".join(f"[{name}] {line}" for line in f.log) + "\n")
        assert not crashed, f"processes of fleet {name} ended abnormally: {json.dumps(crashed, indent=1)}"

    request.addfinalizer(teardown)  # before anything is created
    f.inv("vpn", "init", check=True)
    request.getfixturevalue("clone_images")(data["ros"]["distro"])  # the run's image: every layer cached
    f.inv("snapshot", "build", check=True)
    return f


def wait_for(what: str, probe: Callable[[], tuple[bool, object]], timeout: float, interval: float = 1.0,
             since: float | None = None) -> object:
    """Call probe() until it says done; fail after `timeout` s (from `since`) with its last answer."""
    deadline = (since if since is not None else time.monotonic()) + timeout
    while True:
        done, last = probe()
        if done:
            return last
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {timeout:.0f} s; last seen: {json.dumps(last, default=str)[:1500]}")
        time.sleep(interval)


def connected(fleet: E2EFleet, robot: str) -> Callable[[], tuple[bool, object]]:
    def probe():
        row = fleet.status()[robot]
        return row["vpn_connected"] and f"/{robot}_demo" in row["robot_nodes"], row
    return probe


def exec_in(container, argv: list[str], timeout: int = 30) -> tuple[int, str]:
    # -k: a command that outlives its TERM (rospy's shutdown can hang) is killed 5 s later, else
    # docker's exec stream, and the test reading it, would wait for ever
    result = container.exec_run(["timeout", "-k", "5", str(timeout), *argv])
    return result.exit_code, (result.output or b"").decode(errors="replace")


def ros_sh(container, script: str, timeout: int = 30) -> tuple[int, str]:
    """A fixed shell snippet (no names from input) in the container's ROS 1 environment."""
    return exec_in(container, ["bash", "-c", f"set -a; . /etc/ccrp/ros.env; set +a; {script}"], timeout)


def relay_through(sender, topic: str, receiver, seen_as: str, marker: str, timeout: int = 20) -> tuple[int, str]:
    """Publish `marker` on `topic` in sender until one arrives on `seen_as` in receiver (or
    `timeout` ends); the publisher is stopped as soon as the subscriber returns."""
    from concurrent.futures import ThreadPoolExecutor

    assert marker.replace("-", "").isalnum(), marker  # it reaches pkill's pattern
    with ThreadPoolExecutor(2) as pool:
        # No pause between the two: the publisher repeats at 5 Hz, so the subscriber gets one whenever it is up.
        echo = pool.submit(ros_sh, receiver, f"rostopic echo -n 1 {seen_as}", timeout)
        pool.submit(ros_sh, sender, f"rostopic pub -r 5 {topic} std_msgs/String 'data: {marker}'", timeout - 2)
        try:
            return echo.result()
        finally:  # else leaving the pool waits for the publisher's whole timeout
            stop_publisher(sender, marker)


def stop_publisher(container, marker: str) -> None:
    """End every process of a `rostopic pub ... 'data: <marker>'` exec: KILL, because a TERMed
    rostopic could hang in rospy's shutdown with its `timeout` wrappers TERMed too (CI on c73867e
    waited 80 minutes on one); "[f]ace-..." matches the publisher's command lines, not pkill's own."""
    container.exec_run(["pkill", "-KILL", "-f", f"data: [{marker[0]}]{marker[1:]}"])


TCP_PROBE = r"""
import json, socket, sys
from concurrent.futures import ThreadPoolExecutor
def probe(target):
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.settimeout(3)
    try:
        s.connect((target[0], target[1]))
        return "open"
    except socket.timeout:
        return "timeout"
    except OSError as exc:
        return type(exc).__name__
    finally:
        s.close()
targets = json.loads(sys.argv[1])
with ThreadPoolExecutor(len(targets)) as pool:
    print(json.dumps({f"{h}:{p}": r for (h, p), r in zip(targets, pool.map(probe, targets))}))
"""


# A TCP connect alone proves little for addresses off the container's own networks: this host's
# egress may accept any TCP connection sent to its default gateway (a transparent proxy does
# here). The master is asked who it is instead, which only a real ROS master answers.
MASTER_PROBE = r"""
import json, socket, sys, xmlrpc.client
socket.setdefaulttimeout(4)
out = {}
for url in sys.argv[1:]:
    try:
        code, _, uri = xmlrpc.client.ServerProxy(url).getUri("/ccrp_e2e")
        out[url] = f"master {uri}" if code == 1 else f"code {code}"
    except Exception as exc:
        out[url] = type(exc).__name__
print(json.dumps(out))
"""


def master_probe(container, urls: list[str]) -> dict[str, str]:
    rc, out = exec_in(container, ["python3", "-c", MASTER_PROBE, *urls])
    assert rc == 0, f"master probe failed in {container.name}: {out[-500:]}"
    return json.loads(out.strip().splitlines()[-1])


def tcp_probe(container, targets: list[tuple[str, int]]) -> dict[str, str]:
    rc, out = exec_in(container, ["python3", "-c", TCP_PROBE, json.dumps(targets)])
    assert rc == 0, f"TCP probe failed in {container.name}: {out[-500:]}"
    return json.loads(out.strip().splitlines()[-1])


def agent_journals(fleet: E2EFleet, robots, agent: str = "relay") -> str:
    """An agent's log (unit ccrp-<agent>) and status file on each robot's clone, for a failure message."""
    out = []
    for robot in robots:
        clone = fleet.container("clone", robot)
        _, log = exec_in(clone, ["journalctl", "-u", f"ccrp-{agent}", "--no-pager", "-o", "cat", "-n", "30"])
        _, status = exec_in(clone, ["cat", f"/run/ccrp-{agent}/status.json"])
        out.append(f"--- {agent} agent of {robot}: {status.strip()}\n{log[-1500:]}")
    return "\n".join(out)


CAPTURE = r"""
import socket, subprocess, sys, time
ip, seconds, marker = sys.argv[1], float(sys.argv[2]), sys.argv[3].encode()
iface = next(l.split()[1] for l in subprocess.run(["ip", "-o", "-4", "addr", "show"], capture_output=True,
                                                  text=True).stdout.splitlines() if f" {ip}/" in l)
sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, 0)  # nothing until bound to iface (packet(7))
sock.bind((iface, 0x0003))
sock.settimeout(0.2)
seen, found, deadline = 0, False, time.monotonic() + seconds
while time.monotonic() < deadline:
    try:
        frame = sock.recv(65535)
    except socket.timeout:
        continue
    seen += len(frame)
    found = found or marker in frame
print(iface, seen, found)
"""


# -- what a failing test prints; no process ended abnormally --------------------------------------

# Journal lines of a process that ended abnormally: a core dump, an abort (exit 134: "terminate
# called without an active exception", rclpy's C++ side when a spinning thread outlives the
# interpreter), a segmentation fault, a fatal Python error. Tests stop units on purpose only with
# SIGTERM or SIGKILL, which none of these match.
ABNORMAL = r"code=dumped|status=(6/ABRT|11/SEGV|134)|terminate called|Fatal Python error"
# The units worth reading when a test fails: ccrp's own, transient ones (systemd-run) included,
# OpenVPN's and cloud-init's final stage.
JOURNAL_UNITS = ["-u", "ccrp-*", "-u", "openvpn*", "-u", "cloud-final.service"]


def containers_labelled(client, label: str, running: bool = False) -> list:
    try:
        found = client.containers.list(ignore_removed=True, all=not running, filters={"label": label})
    except docker.errors.DockerException:
        return []
    return sorted(found, key=lambda c: c.name)


def abnormal_exits(client, label: str) -> dict[str, str]:
    """Container name -> its journal's lines of processes that ended abnormally (ABNORMAL), for
    every running container carrying `label` (a fleet's clones and simulated robots)."""
    found = {}
    for c in containers_labelled(client, label, running=True):
        rc, out = exec_in(c, ["sh", "-c", 'journalctl -q --no-pager -o short-monotonic | grep -E -e "$1"', "sh", ABNORMAL])
        if rc == 0 and out.strip():
            found[c.name] = out.strip()[-3000:]
    return found


def diagnostics(client, label: str, lines: int = 60) -> str:
    """What a failing end-to-end test prints about the containers carrying `label`: each one's
    state, its failed units, the journal of ccrp's units and its console (docker logs), so that a
    CI failure can be understood from the output alone."""
    out = []
    for c in containers_labelled(client, label):
        try:
            c.reload()
            out.append(f"===== {c.name} ({c.labels.get('ccrp-role', '?')}): {c.status}")
            if c.status == "running":
                _, failed = exec_in(c, ["systemctl", "--failed", "--no-legend", "--no-pager"], timeout=10)
                out.append(f"--- failed units: {failed.strip() or 'none'}")
                _, journal = exec_in(c, ["journalctl", "-q", "--no-pager", "-o", "short-monotonic", "-n", str(lines),
                                         *JOURNAL_UNITS], timeout=10)
                out.append(f"--- journal (ccrp, openvpn, cloud-final), last {lines} lines:\n{journal.rstrip()}")
            logs = c.logs(tail=lines // 2).decode(errors="replace").rstrip()
            out.append(f"--- console, last {lines // 2} lines:\n{logs}")
        except docker.errors.DockerException as exc:  # gone meanwhile: say so and go on
            out.append(f"===== {c.name}: {type(exc).__name__}")
    return "\n".join(out)


# -- one clone image per distro for the whole run -------------------------------------------------

SNAPSHOT_CACHE = "ccrp-test/snapshot-cache:{distro}"


def ensure_base(client) -> None:
    """ccrp's base image, built as a Noetic fleet's `snapshot build` would if it is missing (a fresh
    machine), once for all the run's workers (the contract harness needs it too)."""
    from ccrp_cli.providers.docker import images
    from ccrp_cli.recipes import platform
    from tests.locks import host_lock

    def missing() -> bool:
        try:
            client.images.get(images.DEFAULT_BASE)
            return False
        except docker.errors.ImageNotFound:
            return True

    if missing():
        with host_lock("ccrp-base"):
            if missing():  # another worker may have built it meanwhile
                packages = sorted(set(images.BASE_PACKAGES + platform("noetic", "debian-bookworm").packages))
                images.build_base_image(client, images.DEFAULT_BASE, packages)


def warm_snapshot(client, distro: str) -> str:
    """Build the clone image of `distro` once, as `ccrp snapshot build` does (same Dockerfile and
    context), and keep it tagged between runs: every fleet's own `snapshot build` then finds each
    layer in Docker's cache and takes seconds. A lock file makes parallel workers build it once."""
    from ccrp_cli.providers.docker import images
    from ccrp_cli.recipes import platform
    from ccrp_cli.services.registry import image_agents
    from tests.fakes.cloudboot import test_run
    from tests.locks import host_lock

    plat = platform(distro, "debian-bookworm")
    tag = SNAPSHOT_CACHE.format(distro=distro)
    ensure_base(client)
    built_by = Path(f"/tmp/ccrp-test-snapshot-{distro}.run")  # beside the lock: the test run that built it last
    with host_lock(f"snapshot-{distro}"):
        # Another worker of this run built it already: its layers are in the cache (a build again
        # would only check that, seconds per worker).
        if built_by.is_file() and built_by.read_text() == test_run() and client.images.list(name=tag):
            return tag
        images.build_clone_image(client, tag, images.dockerfile("cache", distro, images.DEFAULT_BASE, plat, agents=image_agents()),
                                 {"ccrp-test-cache": distro}, files=images.build_context(plat, distro=distro, agents=image_agents()))
        built_by.write_text(test_run())
    return tag


def face_frame() -> bytes:
    """A 320x240 bgr8 frame with a face: Grace Hopper, from matplotlib's sample data (nothing downloaded)."""
    cv2 = pytest.importorskip("cv2")
    mpl = pytest.importorskip("matplotlib")
    img = cv2.imread(str(Path(mpl.get_data_path()) / "sample_data" / "grace_hopper.jpg"))
    return cv2.resize(img[:384], (320, 240)).tobytes()


def face_photo(path: Path) -> Path:
    """Grace Hopper's portrait at another crop and scale than face_frame's: what an operator teaches
    the face-recognition backend (`ccrp knowledge add`, a photo named after the person)."""
    cv2 = pytest.importorskip("cv2")
    mpl = pytest.importorskip("matplotlib")
    portrait = cv2.imread(str(Path(mpl.get_data_path()) / "sample_data" / "grace_hopper.jpg"))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.resize(portrait[20:420, 30:560], (400, 300)))
    return path


# -- the thesis's evaluation, the same on every distro's fleet (test_evaluation, test_jazzy_fleet) --


def check_teleop(rows: dict, link_ms: float) -> None:
    """`bench teleop` rows by stream under a `link_ms` round trip: commands arrive half a round
    trip after they were sent, camera frames come through the link too."""
    command, video = rows["command"], rows["video"]
    assert command["samples"] >= 20 and link_ms / 2 - 2 <= command["p50_ms"] <= link_ms / 2 + 20, command
    assert video["samples"] >= 5 and video["p50_ms"] >= link_ms / 2 - 2, video
    assert command["sent"] >= command["samples"] and video["sent"] >= video["samples"]


def bench_qos_flat(fleet: E2EFleet, stat: str, cbm_max: float) -> None:
    """`bench qos` for 1 and 2 robots on a 40 ms link: with a clone per robot (CBM) the `stat` of
    the response time stays flat, with one shared server (PBM) it grows; the fleet is left as found
    (robot nao2, which the bench starts, removed; nao1's own link back; no bench unit or worker
    rule on the clones)."""
    fleet.inv("robot", "sim", "--robot", "nao1", "--link", "20", check=True)  # nao1's own link, to get back
    try:
        rows = fleet.json("bench", "qos", "--robots", "1..2", "--task-ms", "200", "--duration", "4", "--link", "40")
    finally:
        own = fleet.container("robot-sim", "nao1")
        link_unit = exec_in(own, ["systemctl", "show", "ccrp-link", "--property", "Description", "--value"])[1]
        fleet.inv("robot", "sim", "--robot", "nao1", "--link", "none")
    by = {(r["model"], r["robots"]): r for r in rows}
    assert set(by) == {("cbm", 1), ("cbm", 2), ("pbm", 1), ("pbm", 2)}, rows
    for r in rows:
        assert r["samples"] >= 5 and r["lost"] == 0 and r["task_ms"] == 200 and r["link"] == "40/0/0", r
    cbm1, cbm2, pbm2 = by["cbm", 1][stat], by["cbm", 2][stat], by["pbm", 2][stat]
    assert 240 <= cbm1 <= cbm_max, rows  # the task + the 40 ms round trip
    assert abs(cbm2 - cbm1) / cbm1 < 0.10, rows
    assert pbm2 >= 1.4 * cbm2, rows

    assert not fleet.containers(role="robot-sim", robot="nao2")
    assert link_unit.startswith("20/0/0"), link_unit
    for robot in ("nao1", "nao2"):
        clone = fleet.container("clone", robot)
        for unit in ("ccrp-bench-serve", "ccrp-bench-worker"):
            _, state = exec_in(clone, ["systemctl", "is-active", unit])
            assert state.strip() != "active", (robot, unit)
        _, rules = exec_in(clone, ["iptables", "-w", "-S", "INPUT"])
        assert "7460" not in rules, rules

