"""What a scenario needs from a backend: an inventory written for this run, `ccrp` run as the user
types it, and what the backend still holds carrying the fleet's labels (must be nothing at the end).

One module per backend (backend_<kind>.py) exposes `open_backend(tmp_path, fleet) -> contextmanager
yielding a Backend`; leaving the context removes everything the backend's fake or engine made,
even when the scenario failed. An opt-in backend also exposes `unavailable() -> str | None`: why
its scenario cannot run on this machine (a skip), checked before anything is built for it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest

from tests.conftest import call_started, record_call
from tests.inprocess_cli import run_ccrp_inprocess

ROOT = Path(__file__).resolve().parents[2]


def inventory_text(fleet: str, provider: str, common_cidr: str, vpn_pool: str, distro: str = "noetic") -> str:
    """The thesis lab in small: nao1 exports /faces (on ROS 2: the demo node's /chatter), nao2
    imports it; a template for `fleet scale`."""
    topic = "/faces" if distro == "noetic" else "/chatter"
    return f"""fleet: {fleet}
provider:
{provider.rstrip()}
ros:
  distro: {distro}
vpn:
  pool: {vpn_pool}
common:
  cidr: {common_cidr}
robots:
  - name: nao1
    type: nao
    exports: [{topic}]
  - name: nao2
    type: nao
    imports:
      nao1: [{topic}]
template:
  prefix: robot
  type: generic
  max: 4
"""


# The robot's own software (docs/workloads.md) in small, for a backend whose scenario builds it into
# its snapshot: a catkin package holding one rospy node, which prints a line and publishes /hello
# every 2 s, started the two ways a ROS 1 user starts a node (ROS habits): `rosrun` (unit
# ccrp-run-hello) and `roslaunch` of a launch file naming it /launched (unit ccrp-run-launched).
HELLO_NODE = """#!/usr/bin/env python3
import rospy
from std_msgs.msg import String

rospy.init_node("hello")
pub = rospy.Publisher("/hello", String, queue_size=1, latch=True)
n = 0
while not rospy.is_shutdown():
    print(f"hello {n} from the snapshot's workspace", flush=True)
    pub.publish(String(data=f"hello {n}"))
    n += 1
    rospy.sleep(2.0)
"""
HELLO_WORKSPACE = {
    "src/ccrp_hello/package.xml": """<?xml version="1.0"?>
<package format="2">
  <name>ccrp_hello</name>
  <version>0.0.1</version>
  <description>ccrp's scenario node</description>
  <maintainer email="ccrp@example.org">ccrp</maintainer>
  <license>MIT</license>
  <buildtool_depend>catkin</buildtool_depend>
  <exec_depend>rospy</exec_depend>
</package>
""",
    "src/ccrp_hello/CMakeLists.txt": """cmake_minimum_required(VERSION 3.0.2)
project(ccrp_hello)
find_package(catkin REQUIRED)
catkin_package()
catkin_install_python(PROGRAMS scripts/hello DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION})
install(DIRECTORY launch DESTINATION ${CATKIN_PACKAGE_SHARE_DESTINATION})
""",
    "src/ccrp_hello/scripts/hello": HELLO_NODE,
    "src/ccrp_hello/launch/hello.launch": '<launch><node pkg="ccrp_hello" type="hello" name="launched" output="screen"/></launch>\n',
}
HELLO_SOFTWARE = """software:
  workspace: ws
  run:
    - name: hello
      command: [rosrun, ccrp_hello, hello]
    - name: launched
      command: [roslaunch, ccrp_hello, hello.launch]
"""


def hello_software(directory: Path) -> str:
    """Writes the workspace into `directory`/ws (beside the inventory); returns the inventory's
    `software:` naming it."""
    for rel, text in HELLO_WORKSPACE.items():
        path = directory / "ws" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return HELLO_SOFTWARE


@dataclass
class Backend:
    kind: str
    inventory: Path
    home: Path  # CCRP_HOME of the run
    env: dict[str, str] = field(default_factory=dict)  # what the user's shell would export (OS_CLOUD...)
    # What the backend holds carrying the fleet's labels ("kind id" each); [] once `fleet down` ran.
    owned: Callable[[], list[str]] = lambda: []
    # Fault injection: name -> context manager factory ("quota", "zone", "storm").
    faults: dict[str, Callable] = field(default_factory=dict)
    # Docker network of this host simulated robots of a cloud fleet sit on (reaching public IPs).
    sim_network: str | None = None
    # In-process runner for backends whose fake cannot serve another process (None: subprocess).
    runner: Callable[..., subprocess.CompletedProcess] | None = None
    # Docker labels of the containers the fleet runs in beside its own `ccrp-fleet` one (a fake
    # cloud's servers): what a failing scenario prints the journals and consoles of.
    labels: list[str] = field(default_factory=list)
    # The nodes of the inventory's software: (its snapshot carries them; each clone runs them).
    nodes: list[str] = field(default_factory=list)
    # A fleet with an entry gateway (provider.entry: gateway): deletes the gateway's instance in the
    # cloud, as an operator or a failure would, and returns its public address.
    gateway: Callable[[], str] | None = None

    def ccrp(self, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
        if self.runner is not None:
            return self.runner(*args, timeout=timeout)
        env = {**os.environ, "CCRP_HOME": str(self.home), **self.env}
        env.pop("CCRP_INVENTORY", None)
        started = call_started()
        proc = subprocess.run([sys.executable, "-m", "ccrp_cli", *args], cwd=ROOT, env=env, capture_output=True,
                              text=True, timeout=timeout)
        record_call(args, started, proc.returncode)
        return proc

    def observe(self, *args: str) -> subprocess.CompletedProcess:
        """A read-only command (`status --json`) run in this process: the same command and output
        without a Python start (and the cloud SDK's import) on every poll of a wait. The user's
        own calls go through ccrp() above."""
        if self.runner is not None:
            return self.runner(*args)
        code, out, err = run_ccrp_inprocess(*args, home=self.home, env=self.env)
        return subprocess.CompletedProcess(["ccrp", *args], code, out, err)


@contextmanager
def no_fault():
    yield


def free_cidr(within: str, prefix: int = 24, skip: int = 0) -> str:
    """A /prefix of `within` that no Docker network nor route of this machine uses (the
    backends' networks become Docker networks)."""
    import ipaddress
    import random

    from ccrp_cli.ops.init import host_ranges

    used = [ipaddress.IPv4Network(r) for r in host_ranges()]
    candidates = list(ipaddress.IPv4Network(within).subnets(new_prefix=prefix))
    # Parallel workers of one run (pytest-xdist) pick from disjoint shares: a network is made only
    # later (at `fleet up`), so two workers must never pick the same range meanwhile.
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    count = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    candidates = candidates[int(worker) % count::count] if worker.isdigit() else candidates
    random.shuffle(candidates)  # two runs side by side rarely pick the same
    free = [c for c in candidates if not any(c.overlaps(u) for u in used)]
    if len(free) <= skip:
        raise RuntimeError(f"no free /{prefix} left in {within} for this worker")
    return str(free[skip])


CONNECT = 120  # seconds a simulated robot gets to install its bundle and connect


class Run:
    """A backend plus the steps done so far (a step that needs a failed one is skipped); the
    `run` fixture of a scenario module."""

    def __init__(self, backend, fleet: str) -> None:
        self.b, self.fleet, self.done = backend, fleet, set()

    def ccrp(self, *args: str, code: int = 0, timeout: float = 1200) -> subprocess.CompletedProcess:
        argv = [*args, "-i", str(self.b.inventory)] if args[0] not in ("--help",) else list(args)
        if "--" in args:  # options go before the command of `clone exec ... -- CMD`
            cut = args.index("--")
            argv = [*args[:cut], "-i", str(self.b.inventory), *args[cut:]]
        proc = self.b.ccrp(*argv, timeout=timeout)
        assert "Traceback" not in proc.stderr, f"ccrp {' '.join(args)} printed a traceback:\n{proc.stderr[-3000:]}"
        assert proc.returncode == code, (f"ccrp {' '.join(args)} exited {proc.returncode}, wanted {code}\n"
                                         f"stderr: {proc.stderr[-3000:]}\nstdout: {proc.stdout[-1000:]}")
        return proc

    def json(self, *args: str, code: int = 0):
        return json.loads(self.ccrp(*args, "--json", code=code).stdout)

    def status(self) -> dict[str, dict]:
        proc = self.b.observe("status", "-i", str(self.b.inventory), "--json")
        assert proc.returncode == 0 and "Traceback" not in proc.stderr, f"ccrp status exited {proc.returncode}:\n{proc.stderr[-3000:]}"
        return {r["robot"]: r for r in json.loads(proc.stdout)}

    def needs(self, *steps: str) -> None:
        missing = [s for s in steps if s not in self.done]
        if missing:
            pytest.skip(f"needs the earlier step(s) {', '.join(missing)}")

    @property
    def diagnostic_labels(self) -> list[str]:
        return [f"ccrp-fleet={self.fleet}", *self.b.labels]

    def abnormal_exits(self) -> dict[str, str]:
        """Container -> journal lines of processes that ended abnormally (tests/e2e/fleet.py)."""
        import docker

        from tests.e2e.fleet import abnormal_exits

        client = docker.from_env(timeout=120)
        try:
            return {name: lines for label in self.diagnostic_labels for name, lines in abnormal_exits(client, label).items()}
        finally:
            client.close()


def sim(run: Run, robot: str) -> dict:
    """`ccrp robot sim --robot ROBOT --wait` (on the backend's robot network), its JSON."""
    extra = ["--network", run.b.sim_network] if run.b.sim_network else []
    return run.json("robot", "sim", "--robot", robot, "--wait", str(CONNECT), *extra)
