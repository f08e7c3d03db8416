"""End to end on Docker: the thesis's evaluation as commands, on a two-robot fleet of its own
(`e2v<random>`: nao1 and nao2 of the lab, swept away at the end of the module whatever happens).

  1. `robot sim --link` shapes a running robot's path to its clone in place (the container is not
     recreated), every probe of `bench rtt` sees the added round trip, and `--link none` takes it off
  2. `bench teleop`: commands reach the robot about half a round trip after they were sent
  3. `bench qos`: a clone per robot keeps the response time flat from 1 to 2 robots, one shared
     server doubles it; the fleet is left as found (no simulated robot, unit or firewall rule
     the bench added stays behind, and nao1 gets its own link back)
  4. `status` marks a robot's nodes stale while its session is down; snapshot retention keeps
     the newest (snapshots.keep: 1 here) and what the clones run from; `robot sim --stop`
     without --robot removes every simulated robot of the fleet
"""

from __future__ import annotations

import pytest

from tests.e2e.fleet import CONNECT_TIMEOUT, E2EFleet, bench_qos_flat, check_teleop, exec_in, start_fleet, wait_for

pytestmark = [pytest.mark.slow]

LINK_MS = 80


@pytest.fixture(scope="module")
def fleet(request, tmp_path_factory) -> E2EFleet:
    def two_robots(data: dict) -> None:
        data["robots"] = [r for r in data["robots"] if r["name"] in ("nao1", "nao2")]
        for r in data["robots"]:
            r["imports"] = {k: v for k, v in r.get("imports", {}).items() if k in ("nao1", "nao2")}
        data.pop("template", None)
        data["snapshots"] = {"keep": 1}

    f = start_fleet(request, tmp_path_factory, "e2v", two_robots)
    f.inv("fleet", "up", check=True)
    f.inv("robot", "sim", "--robot", "nao1", "--wait", str(CONNECT_TIMEOUT), check=True)
    return f


def rtt(fleet: E2EFleet) -> dict[str, dict]:
    rows = fleet.json("bench", "rtt", "--robot", "nao1", "--samples", "20")
    return {"public" if r["path"].startswith("public") else r["probe"]: r for r in rows}


def nfqueue_rules(fleet: E2EFleet) -> str:
    _, rules = exec_in(fleet.container("robot-sim", "nao1"), ["iptables", "-w", "-t", "mangle", "-S"])
    return "\n".join(line for line in rules.splitlines() if "NFQUEUE" in line)


def test_link_shapes_a_running_robot_and_comes_off(fleet: E2EFleet):
    before = rtt(fleet)
    assert set(before) == {"public", "icmp", "ros topic"}
    for row in before.values():
        assert row["samples"] >= 19 and row["mean_ms"] < 20, before
    container = fleet.container("robot-sim", "nao1").id

    fleet.inv("robot", "sim", "--robot", "nao1", "--link", str(LINK_MS), check=True)
    assert fleet.container("robot-sim", "nao1").id == container, "the link change recreated the robot"
    shaped = rtt(fleet)
    for probe, row in shaped.items():
        assert LINK_MS - 2 <= row["p50_ms"] <= LINK_MS + 25, (probe, shaped)
        assert row["link"].startswith(f"{LINK_MS}/0/0"), row
    assert nfqueue_rules(fleet)

    fleet.inv("robot", "sim", "--robot", "nao1", "--link", "none", check=True)
    assert not nfqueue_rules(fleet)
    after = rtt(fleet)
    assert all(row["mean_ms"] < 20 for row in after.values()), after


def test_teleop_commands_arrive_half_a_round_trip_later(fleet: E2EFleet):
    fleet.inv("robot", "sim", "--robot", "nao1", "--link", str(LINK_MS), check=True)
    try:
        rows = {r["stream"].split()[0]: r for r in fleet.json("bench", "teleop", "--robot", "nao1", "--duration", "4")}
    finally:
        fleet.inv("robot", "sim", "--robot", "nao1", "--link", "none", check=True)
    check_teleop(rows, LINK_MS)


def test_qos_clone_per_robot_stays_flat_shared_server_does_not(fleet: E2EFleet):
    # Medians, as on Jazzy: in run 37 a few slow replies on this shared 2-core machine (p95 359 ms)
    # moved the 2-robot CBM round's mean 10.4% off the 1-robot one's while its median moved 3.7%.
    bench_qos_flat(fleet, "p50_ms", 290)


def test_status_marks_nodes_stale_while_the_robot_is_not_connected(fleet: E2EFleet):
    """The master keeps a node registered after its robot's session ended: status shows it as
    stale, not as the robot's node, until the robot is back."""
    sim = fleet.container("robot-sim", "nao1")

    def nao1() -> dict:
        return fleet.status()["nao1"]

    assert exec_in(sim, ["systemctl", "stop", "ccrp-vpn"])[0] == 0  # explicit-exit-notify ends the session
    try:
        row = wait_for("nao1's session to end", lambda: (not (r := nao1())["vpn_connected"], r), timeout=20)
        assert row["robot_nodes"] == [] and row["stale_nodes"] == ["/nao1_demo"], row
        text = fleet.inv("status", check=True).stdout
        assert "(stale, robot not connected: /nao1_demo)" in text, text
    finally:
        exec_in(sim, ["systemctl", "start", "ccrp-vpn"])
    row = wait_for("nao1 back", lambda: ((r := nao1())["vpn_connected"] and r["robot_nodes"] == ["/nao1_demo"], r), timeout=CONNECT_TIMEOUT)
    assert row["stale_nodes"] == []


def test_snapshot_build_keeps_the_newest_and_those_clones_run_from(fleet: E2EFleet):
    """snapshots.keep is 1 here. Two captures of clones (`snapshot create`, distinct images), then
    a build (the recipe's image again: Docker's cache gives the same image as the first): the
    build keeps the newest capture and the snapshot both clones run from, and removes the other
    capture; `snapshot list` says who uses which."""
    first = fleet.snapshot_image()
    used = fleet.json("snapshot", "create", "--robot", "nao1", "--use")[0]["name"]
    newest = fleet.json("snapshot", "create", "--robot", "nao2")[0]["name"]
    listed = {r["name"]: r["in_use"] for r in fleet.json("snapshot", "list")}
    assert listed == {first: ["nao1", "nao2"], used: ["new clones"], newest: []}, listed
    proc = fleet.inv("snapshot", "build", check=True)
    assert fleet.snapshot_image() != used
    assert f"removed snapshot {used}" in proc.stderr, proc.stderr
    listed = {r["name"]: r["in_use"] for r in fleet.json("snapshot", "list")}
    assert set(listed) == {first, newest} or set(listed) == {fleet.snapshot_image(), newest}, listed
    assert listed[newest] == [] and sorted(u for v in listed.values() for u in v) == ["nao1", "nao2", "new clones"], listed
    assert not fleet.client.images.list(name=used)


def test_sim_stop_without_robot_removes_every_simulated_robot(fleet: E2EFleet):
    assert fleet.containers(role="robot-sim")
    proc = fleet.inv("robot", "sim", "--stop", check=True)
    assert "removed 1 simulated robot(s)" in proc.stderr and "nao1" in proc.stderr, proc.stderr
    assert not fleet.containers(role="robot-sim")
    assert fleet.inv("robot", "sim").returncode == 2  # only --stop works without --robot
