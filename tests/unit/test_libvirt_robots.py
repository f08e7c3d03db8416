"""Simulated robots of a libvirt fleet without libvirt or Docker: the robots' block kept out of the
NAT network's DHCP range, the address a robot gets, the veth's names and the argument lists that
wire it, the refusal on a remote libvirt host, and `fleet down`/`gc` finding the robots' containers."""

from __future__ import annotations

import ipaddress
import subprocess
import xml.etree.ElementTree as ET

import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.providers.base import owner_labels
from ccrp_cli.providers.libvirt import network, robots, xmldefs
from ccrp_cli.providers.libvirt import owned as owned_module

from .test_libvirt import _Conn, _Pool, inventory, stand_in

NET = ipaddress.IPv4Network("192.168.150.0/24")


def test_robots_block_is_the_top_of_the_network_and_outside_dhcp():
    block = xmldefs.robot_block(NET)
    assert (str(block[0]), str(block[-1]), len(block)) == ("192.168.150.239", "192.168.150.254", 16)
    rng = ET.fromstring(xmldefs.nat_network("n", "b", NET)).find("ip/dhcp/range")
    assert ipaddress.IPv4Address(rng.get("end")) + 1 == block[0]
    # A small network keeps a quarter of its hosts, and DHCP still has the rest.
    small = ipaddress.IPv4Network("192.168.150.0/28")
    assert [str(a) for a in xmldefs.robot_block(small)] == ["192.168.150.12", "192.168.150.13", "192.168.150.14"]
    assert ET.fromstring(xmldefs.nat_network("n", "b", small)).find("ip/dhcp/range").get("end") == "192.168.150.11"


def test_robot_address_by_slot_from_the_top():
    assert str(robots.robot_address(NET, 1, set(), "nao1")) == "192.168.150.254"
    assert str(robots.robot_address(NET, 2, {"192.168.150.254"}, "nao2")) == "192.168.150.253"
    for index in (0, 17):
        with pytest.raises(CcrpError, match="keeps 16 at its top"):
            robots.robot_address(NET, index, set(), "r")
    # A network made before the block: its DHCP range covers it, a lease or reservation there wins.
    with pytest.raises(CcrpError, match="leased or reserved") as err:
        robots.robot_address(NET, 1, {"192.168.150.254"}, "nao1")
    assert "\n" not in err.value.message and "fleet down" in err.value.hint


def test_clone_addresses_stay_out_of_the_robots_block(tmp_path):
    p = stand_in(tmp_path, [], [], [])
    assert p.public_ip("10.90.0.229") == "192.168.150.229"
    with pytest.raises(CcrpError, match="no counterpart"):
        p.public_ip("10.90.0.240")


def test_veth_names_fit_and_differ():
    names = {robots.veth_name(f, r) for f in ("vmlab", "a" * 31) for r in ("nao1", "nao2", "r" * 40)}
    assert len(names) == 6 and all(len(n) <= 15 and n.startswith("ccrpv") for n in names)
    # Never a bridge's name (xmldefs.bridge_name ends with the network's role letter after 8 hex digits).
    assert robots.veth_name("vmlab", "nao1") != xmldefs.bridge_name("vmlab", "public")


@pytest.mark.parametrize("uri", ["qemu+ssh://ops@lab1/system", "qemu:///session", "qemu+tcp://10.0.0.5/system"])
def test_remote_libvirt_is_refused_in_one_line(uri):
    with pytest.raises(CcrpError) as err:
        robots.require_local(uri)
    assert "\n" not in err.value.message and uri in err.value.message and "docs/libvirt.md" in err.value.hint


def test_local_uris_pass():
    for uri in ("qemu:///system", "qemu+unix:///system"):
        robots.require_local(uri)


def port() -> robots.RobotPort:
    return robots.RobotPort(network="ccrp-vmlab-public", bridge="ccrpabcdef01p", veth=robots.veth_name("vmlab", "nao1"),
                            address=ipaddress.IPv4Interface("192.168.150.254/24"))


def test_attach_runs_argument_lists(monkeypatch):
    ran = []

    def run(argv, **kw):
        assert isinstance(argv, list) and "shell" not in kw
        ran.append(argv)
        return subprocess.CompletedProcess(argv, 1 if argv[:3] == ["ip", "link", "del"] else 0, "",
                                           "Cannot find device" if argv[:3] == ["ip", "link", "del"] else "")

    monkeypatch.setattr(robots.subprocess, "run", run)
    p = port()
    p.attach(4242)
    ns = ["nsenter", "--target", "4242", "--net", "--"]
    assert ran == [
        ["ip", "link", "del", p.veth],
        ["ip", "link", "add", p.veth, "type", "veth", "peer", "name", "eth0", "netns", "4242"],
        ["ip", "link", "set", p.veth, "master", "ccrpabcdef01p", "up"],
        [*ns, "ip", "address", "add", "192.168.150.254/24", "dev", "eth0"],
        [*ns, "ip", "link", "set", "eth0", "up"],
    ]  # no default route (robots.py says why)
    assert str(p) == "ccrp-vmlab-public (192.168.150.254)"


def test_attach_failure_removes_the_host_end_and_is_one_line(monkeypatch):
    ran = []

    def run(argv, **kw):
        ran.append(argv)
        failed = argv[-3:] == ["master", "ccrpabcdef01p", "up"]
        return subprocess.CompletedProcess(argv, 2 if failed else 0, "", "Error: no such\nbridge" if failed else "")

    monkeypatch.setattr(robots.subprocess, "run", run)
    with pytest.raises(CcrpError, match="failed: Error: no such bridge") as err:
        port().attach(1)
    assert "\n" not in err.value.message and ran[-1] == ["ip", "link", "del", port().veth]


class _NatNet:
    def __init__(self, xml, leases=(), active=True):
        self.xml, self.leases, self.active = xml, list(leases), active

    def name(self):
        return ET.fromstring(self.xml).findtext("name")

    def isActive(self):
        return self.active

    def XMLDesc(self, flags):
        return self.xml

    def DHCPLeases(self):
        return self.leases

    def bridgeName(self):
        return ET.fromstring(self.xml).find("bridge").get("name")


class _NetConn(_Conn):
    def networkLookupByName(self, name):
        return next(n for n in self.nets if n.name() == name)


def bridged(tmp_path, net, uri="qemu:///system"):
    p = stand_in(tmp_path, [], [], [])
    if uri != "qemu:///system":
        p.inv = p.client.inv = inventory(tmp_path, uri=uri)
        p.settings = p.client.settings = p.inv.provider
    p.client.conn = _NetConn([], _Pool([]), [net])
    return p


def test_robot_port_on_the_fleets_nat_network(tmp_path):
    xml = xmldefs.nat_network("ccrp-vmlab-public", xmldefs.bridge_name("vmlab", "public"), NET)
    p = bridged(tmp_path, _NatNet(xml))
    got = network.robot_port(p.client, "nao2", 2)
    assert (got.network, got.bridge, str(got.address)) == (
        "ccrp-vmlab-public", xmldefs.bridge_name("vmlab", "public"), "192.168.150.253/24")
    # An older network (DHCP to .254) that leased the robot's address refuses it.
    old = ET.fromstring(xml)
    old.find("ip/dhcp/range").set("end", "192.168.150.254")
    p = bridged(tmp_path, _NatNet(ET.tostring(old, encoding="unicode"), [{"ipaddr": "192.168.150.254"}]))
    with pytest.raises(CcrpError, match="leased or reserved"):
        network.robot_port(p.client, "nao1", 1)
    p = bridged(tmp_path, _NatNet(xml, active=False))
    with pytest.raises(CcrpError, match="no running network") as err:
        network.robot_port(p.client, "nao1", 1)
    assert "fleet up" in err.value.hint


def test_robot_port_refused_for_a_remote_host_before_asking_it(tmp_path):
    p = bridged(tmp_path, None, uri="qemu+ssh://ops@lab1/system")
    with pytest.raises(CcrpError, match="not this machine"):
        network.robot_port(p.client, "nao1", 1)


class _Container:
    def __init__(self, cid, name, role, robot, fleet="vmlab"):
        self.id, self.name, self.labels = cid, name, owner_labels(fleet, role, robot)
        self.removed = False

    def remove(self, force, v):
        self.removed = True


def test_fleet_down_and_gc_find_the_robots_containers(tmp_path, monkeypatch):
    from ccrp_cli.ops.gc import find_leaks
    from ccrp_cli.models.state import FleetState

    sims = [_Container("a" * 64, "ccrp-vmlab-nao1", "robot-sim", "nao1"),
            _Container("b" * 64, "ccrp-vmlab-nao1-power", "power-sim", "nao1"),
            _Container("c" * 64, "ccrp-vmlab-nao9", "robot-sim", "nao9"),
            _Container("d" * 64, "ccrp-vmlab-cri-nao1", "clone", "nao1")]  # a Docker fleet's clone: not a sim
    p = stand_in(tmp_path, [], [], ["ccrp-vmlab-public"])
    monkeypatch.setattr(owned_module, "sims", lambda c: [s for s in sims if s.labels["ccrp-role"] in ("robot-sim", "power-sim")])
    owned = p.list_owned()
    assert [(r.kind, r.name) for r in owned] == [
        ("robot_sim", "ccrp-vmlab-nao1-power"), ("robot_sim", "ccrp-vmlab-nao1"), ("robot_sim", "ccrp-vmlab-nao9"),
        ("network", "ccrp-vmlab-public")]
    assert "container ccrp-vmlab-nao1" in p.leftovers()
    state = FleetState.model_validate({"fleet": "vmlab", "robots": {"nao1": {"index": 1}}})
    assert [r.name for r in find_leaks(state, owned, [])] == ["ccrp-vmlab-nao9"]  # gc: a robot the fleet lost
    released = []
    monkeypatch.setattr(network, "release_robot_port", lambda c, robot: released.append(robot))
    p.delete_owned(owned[2])
    assert sims[2].removed and not sims[0].removed and released == ["nao9"]  # its veth, if the kernel kept it
    with pytest.raises(CcrpError, match="gone or not fleet"):
        p.delete_owned(owned[2].model_copy(update={"id": "d" * 12}))  # the clone container is never a sim


def test_a_reservation_is_deleted_without_a_name():
    """libvirt refuses `name=''` ("Cannot use host name ''"), which made every rollback of a clone
    fail and hid why its `fleet up` had failed."""
    assert ET.fromstring(xmldefs.dhcp_host("52:54:00:00:00:01", "192.168.150.10")).attrib == {
        "mac": "52:54:00:00:00:01", "ip": "192.168.150.10"}


def test_bootstrap_makes_the_operator_key_before_any_clone(tmp_path):
    """Clones are made in parallel: without a key made first, each made its own and all but the last
    written refused ccrp's SSH (seen in the two-clone e2e run)."""
    p = stand_in(tmp_path, [], [], [])
    done = []
    p.operator_public_key = lambda: done.append("key")

    def pool(create=False):
        done.append("pool")
        raise CcrpError("stop here")

    p.client.pool = pool
    with pytest.raises(CcrpError, match="stop here"):
        p.bootstrap()
    assert done == ["key", "pool"]


def test_release_deletes_the_host_end_if_there(monkeypatch):
    ran = []
    monkeypatch.setattr(robots.subprocess, "run", lambda argv, **kw: ran.append(argv) or subprocess.CompletedProcess(
        argv, 1, "", "Cannot find device"))
    robots.release("vmlab", "nao1")
    assert ran == [["ip", "link", "del", robots.veth_name("vmlab", "nao1")]]
