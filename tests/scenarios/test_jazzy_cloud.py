"""A ROS 2 Jazzy fleet on a cloud, as a user runs it: OpenStack through its fake, whose servers
really boot (tests/fakes/cloudboot.py), with the real openstacksdk.

`snapshot bake` boots a builder from the stock Debian 12 image, whose cloud-init installs the
recipe's packages and the ros-jazzy-* wheels from the index into the venv at /opt/ros/jazzy
(snapshots/jazzy.yaml), and captures it; `fleet up` boots nao1's and nao2's clones from it; the
simulated robot nao1 connects to its clone's public address through OpenVPN, its node shows on
its clone's graph, and its /chatter, exported, reaches nao2's clone as /nao1/chatter through the
relays on the cloud's network. `fleet down` leaves nothing of the fleet on the cloud.
"""

from __future__ import annotations

import secrets

import pytest

from tests.e2e.fleet import NO_DOCKER
from tests.scenarios import backend_openstack
from tests.scenarios.backend import Run, sim

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(NO_DOCKER is not None, reason=f"needs a running Docker engine ({NO_DOCKER})"),
]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    # No shared full install first (conftest.py baked_recipes): this is the run's only bake of the
    # Jazzy recipe, so its builder installs everything on the stock image itself; a shared install
    # would only add a second builder that runs the same user-data again (23 s of CPU measured).
    fleet = f"scj{secrets.token_hex(2)}"
    with backend_openstack.open_backend(tmp_path_factory.mktemp("scenario-jazzy"), fleet, distro="jazzy") as backend:
        r = Run(backend, fleet)
        try:
            yield r
        finally:
            if "down" not in r.done:
                r.b.ccrp("robot", "sim", "--stop", "-i", str(backend.inventory))
                r.b.ccrp("fleet", "down", "-i", str(backend.inventory))


def test_a_jazzy_fleet_bakes_boots_connects_and_shares_on_openstack(run):
    run.ccrp("vpn", "init")
    run.ccrp("snapshot", "bake", timeout=1800)
    snaps = run.json("snapshot", "list")
    assert len(snaps) == 1 and f"-{run.fleet}-jazzy-" in snaps[0]["name"], snaps
    assert {r["robot"]: r["action"] for r in run.json("fleet", "up")} == {"nao1": "created", "nao2": "created"}
    rows = run.status()
    for robot in ("nao1", "nao2"):  # the graph in place of the master: the clone's ROS 2 answered
        assert rows[robot]["master_reachable"] is True and rows[robot]["ros_distro"] == "jazzy", rows[robot]

    assert sim(run, "nao1")["nodes"] == ["/nao1_demo"]
    row = run.status()["nao1"]
    assert row["vpn_connected"] and "/nao1_demo" in row["robot_nodes"], row
    # ccrp-topic comes with the snapshot: nao2's clone gets nao1's /chatter from its relay.
    out = run.ccrp("clone", "exec", "--robot", "nao2", "--", "ccrp-topic", "echo", "/nao1/chatter", "-n", "2",
                   "-t", "60").stdout
    assert out.count('{"data": "hello from nao1 #') == 2, out
    assert run.status()["nao2"]["relay_peers"] == {"nao1": True}

    assert not run.abnormal_exits()  # no agent on the clones or the robot aborted (rclpy at exit)

    run.ccrp("robot", "sim", "--stop")
    run.ccrp("fleet", "down")
    run.done.add("down")
    assert run.b.owned() == []
