"""Simulated robots sit where their fleet's backend says (Ability.ROBOT_ATTACH: a RobotAttachment),
in containers of this host's engine whatever the backend (providers.robot_host): robot/simulated.py
names no backend. The engine and the backends are faked; Docker and libvirt answer the same call."""

from __future__ import annotations

import dataclasses

import pytest

from ccrp_cli import providers
from ccrp_cli.errors import InputError
from ccrp_cli.providers.base import RobotAttachment
from ccrp_cli.robot import robots
from ccrp_cli.robot.simulated import Sims

SNAPSHOT = "ccrp/lab-clone:7"


class Host:
    """This host's engine as Sims uses it (base.RobotHost)."""

    def __init__(self):
        self.started: list = []
        self.stopped: list = []

    def robot_image(self, distro, progress):
        return f"ccrp/robot-sim:{distro}"

    def start(self, robot, image, bundle, demo_node, attachment, python):
        self.started.append((robot, image, attachment))
        return "c0ffee"

    def stop(self, robot):
        self.stopped.append(robot)
        return True


class Attaching:
    """A provider with Ability.ROBOT_ATTACH."""

    def __init__(self, seat: RobotAttachment):
        self.seat, self.asked, self.detached = seat, [], []

    def attach_robot(self, robot, index):
        self.asked.append((robot, index))
        return self.seat

    def detach_robot(self, robot):
        self.detached.append(robot)


@pytest.fixture
def lab(lab_up, monkeypatch):
    """The lab fleet (Docker) with a snapshot, its robots' bundles and this host's engine faked."""
    fleet, state = lab_up
    state.snapshot = {"image": SNAPSHOT}
    fleet.store.save_state(state)
    host = Host()
    monkeypatch.setattr(providers, "robot_host", lambda name: host)
    # The public endpoint, unless told another address (a robot on the clones' own network: theirs).
    monkeypatch.setattr(robots, "edge_files", lambda fleet, robot, remote=None: (
        [], remote or fleet.store.load_state().robots[robot].public_endpoint or "203.0.113.9:1194"))
    return fleet, state, host


def test_a_robot_on_the_fleets_own_network_runs_what_the_backend_says(lab):
    fleet, state, host = lab
    provider = Attaching(RobotAttachment(network="lab-public", clone_image=True))  # Docker's answer
    got = Sims(fleet, provider).start("nao1")
    assert host.started == [("nao1", SNAPSHOT, provider.seat)]
    assert provider.asked == [("nao1", state.robots["nao1"].index)]
    assert (got["container"], got["network"]) == ("c0ffee", "lab-public")
    # Outside the fleet's network the clone has no way in (no forward: its endpoint is its address there).
    with pytest.raises(InputError, match="--network puts the robot outside the docker fleet's own network"):
        Sims(fleet, provider).start("nao1", network="bridge")
    assert Sims(fleet, provider).stop("nao1") and provider.detached == ["nao1"] and host.stopped == ["nao1"]


def test_a_robot_outside_a_forwarding_fleets_network_dials_the_forward(lab):
    """libvirt with provider.vpn_forward: the clone's public endpoint is a port of the host, its
    address on the NAT network another. A robot on the NAT network dials the address there; one on a
    network of this host (--network) dials the forward, as a robot on the LAN does."""
    fleet, state, host = lab
    rec = state.robots["nao2"]
    rec.public_endpoint, rec.addresses = "198.51.100.7:11952", {**rec.addresses, "public": "192.168.150.12"}
    fleet.store.save_state(state)
    seat = RobotAttachment(network="none", name="ccrp-lab-public", address="192.168.150.254", attach=lambda pid: None)
    provider = Attaching(seat)
    said: list[str] = []
    Sims(fleet, provider).start("nao2", progress=said.append)
    assert said[0].endswith("dials 192.168.150.12 from 192.168.150.254 on ccrp-lab-public")
    said.clear()
    got = Sims(fleet, provider).start("nao2", network="lab-lan", progress=said.append)
    assert said[0].endswith("dials 198.51.100.7:11952") and got["network"] == "lab-lan"
    assert [str(a) for _, _, a in host.started] == ["ccrp-lab-public (192.168.150.254)", "lab-lan"]
    assert provider.asked == [("nao2", rec.index)]  # the robot outside took no port on the NAT network


def test_a_port_the_backend_wires_gets_the_robots_own_image(lab):
    fleet, state, host = lab
    state.robots["nao2"].addresses = {"public": "192.168.150.12"}
    fleet.store.save_state(state)
    seat = RobotAttachment(network="none", name="ccrp-lab-public", address="192.168.150.254", attach=lambda pid: None)
    said: list[str] = []
    got = Sims(fleet, Attaching(seat)).start("nao2", progress=said.append)  # libvirt's answer
    assert host.started == [("nao2", f"ccrp/robot-sim:{fleet.inventory.ros.distro}", seat)]
    assert got["network"] == "ccrp-lab-public (192.168.150.254)"
    # its clone's address on the network it sits on
    assert said[0].endswith("dials 192.168.150.12 from 192.168.150.254 on ccrp-lab-public")


def test_a_cloud_fleets_robot_dials_from_a_network_of_this_host(lab, monkeypatch):
    fleet, _, host = lab
    cloudlike = dataclasses.replace(providers.info("docker"), abilities=frozenset())
    monkeypatch.setattr(providers, "info", lambda kind: cloudlike)
    provider = Attaching(RobotAttachment(network="unused"))
    Sims(fleet, provider).start("nao1")
    Sims(fleet, provider).start("nao2", network="lab-net")
    assert [(r, str(a), a.attach) for r, _, a in host.started] == [("nao1", "bridge", None), ("nao2", "lab-net", None)]
    assert provider.asked == []
    Sims(fleet, provider).stop("nao1")
    assert provider.detached == []  # nothing of the backend's to let go of


def test_docker_and_libvirt_answer_the_same_call(tmp_path, monkeypatch):
    from ccrp_cli.providers.docker.client import DockerHost
    from ccrp_cli.providers.docker.provider import DockerProvider
    from ccrp_cli.providers.libvirt import network, xmldefs

    from .test_libvirt_robots import NET, _NatNet, bridged

    class Offline(DockerProvider):
        def __init__(self):  # no engine: attach_robot asks none
            self.client = DockerHost.__new__(DockerHost)
            self.fleet = self.client.fleet = "lab"

    seat = Offline().attach_robot("nao1", 1)
    assert (seat.network, seat.clone_image, seat.attach, str(seat)) == ("lab-public", True, None, "lab-public")
    p = bridged(tmp_path, _NatNet(xmldefs.nat_network("ccrp-vmlab-public", xmldefs.bridge_name("vmlab", "public"), NET)))
    seat = p.attach_robot("nao2", 2)
    assert (seat.network, str(seat), seat.clone_image) == ("none", "ccrp-vmlab-public (192.168.150.253)", False)
    assert seat.attach is not None
    released: list[str] = []
    monkeypatch.setattr(network, "release_robot_port", lambda c, robot: released.append(robot))
    p.detach_robot("nao2")
    assert released == ["nao2"]


def test_this_hosts_engine_is_found_by_its_factories():
    """providers.robot_host and build_workspace load their code when first used: the names hold."""
    from ccrp_cli.providers.base import RobotHost

    host = providers._load(providers.ROBOT_HOST)
    assert all(callable(getattr(host, n, None)) for n in dir(RobotHost) if not n.startswith("_"))
    assert callable(providers._load(providers.WORKSPACE_BUILD))
