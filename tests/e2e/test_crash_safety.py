"""Concurrent and interrupted runs on Docker, for real (issue 11).

  1. `ccrp fleet scale` killed with SIGKILL at three moments (growing, shrinking, and growing as
     a new clone's secrets land): the state file still parses and the next `fleet scale`
     converges, with no duplicate clone and no orphan container or volume (bench/crash_scale.py's
     trial, three times)
  2. two `ccrp fleet up` at once: the second says whom it waits for, then reuses what the first
     made; both exit 0 and the fleet is consistent

The module works on a fleet of its own (`crash<random>`, own subnets and CCRP_HOME); a finalizer
runs `ccrp fleet down` and removes everything labelled with that fleet, even when a test fails.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time

import pytest

from tests.conftest import ROOT
from tests.e2e.crash import CrashFleet

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(shutil.which("docker") is None, reason="needs the Docker CLI and engine"),
]
docker = pytest.importorskip("docker", reason="the Docker SDK (`pip install docker`) is not installed")


@pytest.fixture(scope="module")
def crash_fleet(request, clone_images):
    try:
        docker.from_env(timeout=20).ping()
    except Exception as exc:  # noqa: BLE001
        pytest.skip(f"needs a running Docker engine ({type(exc).__name__})")
    fleet = CrashFleet.create()

    def teardown() -> None:
        left = fleet.cleanup()
        print("\n" + "\n".join(f"[{fleet.name}] {line}" for line in fleet.log))
        assert not left, f"could not remove {left}"

    request.addfinalizer(teardown)  # before anything is created
    clone_images("noetic")  # its snapshot build then comes from Docker's cache
    fleet.prepare()
    fleet.check_call("fleet", "scale", "2")
    return fleet


# From 2 clones: killed while adding two, while removing three, and (aimed) as the first new
# clone's secrets land, before OpenVPN restarts with them: that one failed on every later run
# before the secrets got their completion marker (render/files.applied_marker).
@pytest.mark.parametrize(("size", "delay", "aimed"), [(4, 2.5, False), (1, 1.2, False), (3, 0.0, True)],
                         ids=["grow-to-4", "shrink-to-1", "grow-to-3-as-secrets-land"])
def test_fleet_scale_killed_converges_on_next_run(crash_fleet, size, delay, aimed):
    trial = crash_fleet.trial(0, size, len(crash_fleet.state_robots()), delay, aimed)
    crash_fleet.log.append(f"trial: {trial['left']} -> {trial['rerun']['exit']} in {trial['rerun']['convergence_s']}s")
    left, rerun = trial["left"], trial["rerun"]
    assert left["state_parses"], left.get("state_error")
    assert rerun["exit"] == 0 and not rerun["failed"], rerun
    assert not rerun["waited_for_lock"], "the killed run's lock outlived it"
    assert not rerun["problems"], rerun["problems"]
    assert trial["ok"], trial


def test_two_fleet_ups_at_once_the_second_waits_then_reuses(crash_fleet):
    robots = sorted(crash_fleet.state_robots())
    # Give the first run work to do: the clone of one robot is gone.
    gone = robots[-1]
    for c in crash_fleet.client.containers.list(ignore_removed=True, all=True, filters={"label": [
            f"ccrp-fleet={crash_fleet.name}", "ccrp-role=clone", f"ccrp-robot={gone}"]}):
        c.remove(force=True, v=True)
    lock = crash_fleet.home / crash_fleet.name / ".lock"
    env = crash_fleet.env()
    first = subprocess.Popen(crash_fleet.argv("fleet", "up", "--json"), cwd=ROOT, env=env, text=True,
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while not (lock.exists() and lock.read_text().startswith(f"{first.pid} ")):
            assert first.poll() is None, f"the first fleet up ended before taking the lock: {first.communicate()}"
            assert time.monotonic() < deadline, "the first fleet up did not take the lock within 60 s"
            time.sleep(0.05)
        second = subprocess.run(crash_fleet.argv("fleet", "up", "--json"), cwd=ROOT, env=env, text=True,
                                capture_output=True, timeout=600)
        out1, err1 = first.communicate(timeout=600)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert first.returncode == 0, err1[-2000:]
    assert second.returncode == 0, second.stderr[-2000:]
    waiting = f"ccrp: waiting for ccrp run pid {first.pid} (fleet up) to finish with fleet '{crash_fleet.name}'..."
    assert second.stderr.splitlines().count(waiting) == 1, second.stderr[-2000:]
    assert {r["robot"]: r["action"] for r in json.loads(out1)}[gone] == "created", out1
    assert {r["robot"]: r["action"] for r in json.loads(second.stdout)} == dict.fromkeys(robots, "reused"), second.stdout
    found = crash_fleet.check(len(robots))
    assert not found["problems"], found["problems"]
