"""Robots outside the libvirt host (provider.vpn_forward): the settings, the host's netfilter rules
(made, kept, replaced and removed with real iptables in a network namespace of the test's own), and
what the provider does with them: the clone's endpoint, `fleet down`'s and `gc`'s view."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from ccrp_cli.errors import CcrpError, InputError
from ccrp_cli.providers.libvirt import forward, network

from ccrp_cli.providers.base import owner_labels

from .test_libvirt import _Dom, inventory, stand_in

FORWARD = {"address": "198.51.100.7", "base_port": 11940}


def test_vpn_forward_settings(tmp_path):
    p = inventory(tmp_path, vpn_forward=FORWARD).provider
    assert str(p.vpn_forward.address) == "198.51.100.7" and p.vpn_forward.base_port == 11940
    assert inventory(tmp_path, vpn_forward={"address": "198.51.100.7"}).provider.vpn_forward.base_port == 11940
    assert inventory(tmp_path).provider.vpn_forward is None


@pytest.mark.parametrize("settings,says", [
    ({"vpn_forward": {"address": "127.0.0.1"}}, "not an address robots can dial"),
    ({"vpn_forward": {"address": "0.0.0.0"}}, "not an address robots can dial"),
    ({"vpn_forward": {"address": "not-an-ip"}}, "vpn_forward.address"),
    ({"vpn_forward": {"address": "192.168.150.1"}}, "is in provider.public_cidr"),
    ({"vpn_forward": {"address": "198.51.100.7", "base_port": 80}}, "base_port"),
    ({"vpn_forward": {"address": "198.51.100.7", "base_port": 62000}, "public_cidr": "192.168.144.0/20"}, "leaves no port"),
    ({"vpn_forward": {"address": "198.51.100.7", "extra": 1}}, "extra"),
    ({"vpn_forward": FORWARD, "uri": "qemu+ssh://ops@lab1/system"}, "another machine's libvirt"),
])
def test_bad_vpn_forward_is_one_line(tmp_path, settings, says):
    with pytest.raises(InputError) as err:
        inventory(tmp_path, **settings)
    assert says in err.value.one_line() and "\n" not in err.value.one_line()


def test_each_clone_gets_the_port_of_its_place_in_the_plan(tmp_path):
    p = stand_in(tmp_path, [], [], [], settings={"vpn_forward": FORWARD})
    fw = network.vpn_forward(p.client, "nao1", "10.90.0.10")  # common.cidr 10.90.0.0/24: offset 10, public .10
    assert (fw.endpoint, fw.clone_ip, fw.vpn_port, fw.proto) == ("198.51.100.7:11950", "192.168.150.10", 1194, "udp")
    assert str(fw) == "udp 198.51.100.7:11950 -> 192.168.150.10:1194"
    assert network.vpn_forward(p.client, "nao2", "10.90.0.11").port == 11951
    assert network.vpn_forward(stand_in(tmp_path, [], [], []).client, "nao1", "10.90.0.10") is None  # no vpn_forward: none
    nat, filt = fw.rules()
    assert nat == ("nat", ["PREROUTING", "-d", "198.51.100.7/32", "-p", "udp", "-m", "udp", "--dport", "11950", "-m", "comment",
                           "--comment", "ccrp:vmlab:nao1", "-j", "DNAT", "--to-destination", "192.168.150.10:1194"])
    # Only what that DNAT sent, only to the clone's VPN port.
    assert filt == ("filter", ["FORWARD", "-d", "192.168.150.10/32", "-p", "udp", "-m", "udp", "--dport", "1194", "-m", "conntrack",
                               "--ctstate", "DNAT", "-m", "comment", "--comment", "ccrp:vmlab:nao1", "-j", "ACCEPT"])


def test_the_clones_record_names_the_forward_as_its_endpoint(tmp_path, monkeypatch):
    p = stand_in(tmp_path, [], [_Dom("ccrp-vmlab-cri-nao1", owner_labels("vmlab", "clone", "nao1"), "uuid-1")], [],
                 settings={"vpn_forward": FORWARD})
    monkeypatch.setattr(network, "reserved", lambda c, mac: "192.168.150.10")
    rec = p.query()["nao1"]
    assert (rec.public_ip, rec.endpoint) == ("192.168.150.10", "198.51.100.7:11950")


def test_forwards_are_owned_leak_with_their_clone_and_go_with_fleet_down(tmp_path, monkeypatch):
    """One port_forward per robot with rules; a robot without a clone's is a leak for gc; teardown
    (fleet down) removes them all; another fleet's are not listed."""
    from ccrp_cli.models.state import FleetState
    from ccrp_cli.ops.gc import find_leaks

    rules = {("nat", "ccrp:vmlab:nao1"), ("filter", "ccrp:vmlab:nao1"), ("nat", "ccrp:vmlab:nao2")}
    removed: list = []

    def listed(fleet, robot=None):
        return [(t, ["X", "--comment", c]) for t, c in sorted(rules)
                if c.startswith(forward.comment(fleet, robot or ""))]

    def remove(fleet, robot=None):
        gone = listed(fleet, robot)
        removed.append((fleet, robot))
        rules.difference_update((t, spec[-1]) for t, spec in gone)
        return len(gone)

    monkeypatch.setattr(forward, "listed", listed)
    monkeypatch.setattr(forward, "remove", remove)
    p = stand_in(tmp_path, [], [_Dom("ccrp-vmlab-cri-nao1", owner_labels("vmlab", "clone", "nao1"), "uuid-1")], [],
                 settings={"vpn_forward": FORWARD})
    owned = [r for r in p.list_owned() if r.kind == "port_forward"]
    assert [(r.id, r.robot) for r in owned] == [("ccrp:vmlab:nao1", "nao1"), ("ccrp:vmlab:nao2", "nao2")]
    state = FleetState.model_validate({"fleet": "vmlab", "robots": {"nao1": {"index": 1, "provider_id": "uuid-1", "phase": "ready"}}})
    assert [r.id for r in find_leaks(state, owned, []) if r.kind == "port_forward"] == ["ccrp:vmlab:nao2"]
    assert "port forward ccrp:vmlab:nao2" in p.leftovers()
    with pytest.raises(CcrpError, match="not fleet 'vmlab'"):
        p.delete_owned(owned[0].model_copy(update={"id": "ccrp:other:nao1"}))
    p.delete_owned(owned[1])
    assert removed == [("vmlab", "nao2")] and ("nat", "ccrp:vmlab:nao2") not in rules
    with pytest.raises(CcrpError, match="is gone"):
        p.delete_owned(owned[1])


def test_the_forward_address_must_be_this_machines(tmp_path):
    network.check_forward_address("127.0.0.1")
    with pytest.raises(CcrpError, match="is not an address of this machine") as err:
        network.check_forward_address("198.51.100.7")  # TEST-NET-2: no host has it
    assert "ip -4 address" in err.value.hint


# Run in a network namespace of its own, so this host's own firewall is neither read nor changed.
IN_NETNS = r"""
import json, sys
from ccrp_cli.providers.libvirt import forward as f
out = {}
a = f.Forward("lv1", "nao1", "198.51.100.7", 11950, "192.168.150.10", 1194, "udp")
out["made"], out["again"] = f.ensure(a), f.ensure(a)
out["listed"] = f.listed("lv1")
f.ensure(f.Forward("lv1", "nao2", "198.51.100.7", 11951, "192.168.150.11", 1194, "udp"))
f.ensure(f.Forward("lv10", "nao1", "198.51.100.7", 11960, "192.168.160.10", 1194, "udp"))  # another fleet, a name alike
moved = f.Forward("lv1", "nao1", "198.51.100.7", 11950, "192.168.150.20", 1194, "udp")  # its clone's address changed
out["moved"] = f.ensure(moved)
out["nao1"] = f.listed("lv1", "nao1")
out["removed_nao1"] = f.remove("lv1", "nao1")
out["left"] = sorted(f.robot_of(spec) + "@" + t for t, spec in f.listed("lv1"))
out["removed_fleet"] = f.remove("lv1")
out["other"] = len(f.listed("lv10"))
print(json.dumps(out))
"""


@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("iptables") or not shutil.which("unshare"),
                    reason="needs root, iptables and unshare (a network namespace of the test's own)")
def test_rules_with_real_iptables_in_a_namespace():
    proc = subprocess.run(["unshare", "--net", sys.executable, "-c", IN_NETNS], capture_output=True, text=True,
                          timeout=120, cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["made"] is True and out["again"] is False  # idempotent
    a = forward.Forward("lv1", "nao1", "198.51.100.7", 11950, "192.168.150.10", 1194, "udp")
    assert out["listed"] == [[t, spec] for t, spec in a.rules()]  # iptables -S reads back what was made
    assert out["moved"] is True
    moved = forward.Forward("lv1", "nao1", "198.51.100.7", 11950, "192.168.150.20", 1194, "udp")
    assert out["nao1"] == [[t, spec] for t, spec in moved.rules()]  # the old pair went
    assert out["removed_nao1"] == 2 and out["left"] == ["nao2@filter", "nao2@nat"]
    assert out["removed_fleet"] == 2 and out["other"] == 2  # lv10's stayed
