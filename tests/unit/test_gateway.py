"""The entry gateway's files (render/gateway.py): one port per robot for the robot's life, rules that
open those ports and SSH from the operator only, and a cloud-config cloud-init accepts. The rules
carrying a real tunnel, and nothing else, are tests/e2e/test_entry_gateway.py."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from ccrp_cli.fleet import Fleet
from ccrp_cli.models.addressing import entry_port, gateway_ip
from ccrp_cli.render import gateway

INVENTORIES = sorted((Path(__file__).resolve().parents[2] / "inventories").glob("*.yaml"))
KEY = "ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFakeKeyForSchemaOnly operator"


def plan(fleet: Fleet):
    state = fleet.load_allocated()
    return [a for a in fleet.plan(state).values()]


@pytest.mark.parametrize("inventory", INVENTORIES, ids=lambda p: p.stem)
def test_each_robot_has_its_own_port_to_its_own_clone(ccrp_home, inventory):
    fleet = Fleet.open(inventory)
    inv, addrs = fleet.inventory, plan(fleet)
    found = gateway.entries(inv, addrs)
    assert [e.robot for e in found] == [a.robot for a in sorted(addrs, key=lambda a: a.index)]
    assert len({e.port for e in found}) == len(found) and inv.vpn.port not in {e.port for e in found}
    text = gateway.rules(inv, found, "203.0.113.0/24")
    for a in addrs:
        port = entry_port(inv, a.index)
        assert (f"-A PREROUTING -p {inv.vpn.proto} -m {inv.vpn.proto} --dport {port} -m comment --comment \"ccrp:{a.robot}\" "
                f"-j DNAT --to-destination {a.common_ip}:{inv.vpn.port}") in text
    # Nothing reaches the gateway itself but SSH from the operator's range (and ICMP, replies).
    opened = re.findall(r"^-A INPUT .*--dport (\d+).*-j ACCEPT$", text, re.M)
    assert opened == ["22"] and "-A INPUT -p tcp -s 203.0.113.0/24 --dport 22 -j ACCEPT" in text
    assert ":INPUT DROP" in text and ":FORWARD DROP" in text
    assert gateway_ip(inv) in inv.common.cidr and gateway_ip(inv) not in {a.common_ip for a in addrs}


def test_a_robots_port_outlives_the_others(ccrp_home, tmp_path):
    """Ports follow the robots' slots: removing a robot closes its port and moves no other."""
    from tests.conftest import LAB

    fleet = Fleet.open(LAB)
    before = {e.robot: e.port for e in gateway.entries(fleet.inventory, plan(fleet))}
    assert len(before) >= 2
    gone = sorted(before)[0]
    state = fleet.load_allocated()
    kept = [a for name, a in fleet.plan(state).items() if name != gone]
    after = {e.robot: e.port for e in gateway.entries(fleet.inventory, kept)}
    assert after == {r: p for r, p in before.items() if r != gone}


@pytest.mark.skipif(shutil.which("cloud-init") is None, reason="cloud-init not installed (apt-get install cloud-init)")
@pytest.mark.parametrize("inventory", INVENTORIES, ids=lambda p: p.stem)
def test_the_gateway_user_data_passes_cloud_init_schema(ccrp_home, tmp_path, inventory):
    fleet = Fleet.open(inventory)
    text = gateway.user_data(fleet.inventory, gateway.entries(fleet.inventory, plan(fleet)), "0.0.0.0/0", [KEY])
    assert text.startswith("#cloud-config\n") and "PRIVATE KEY" not in text and "password" not in text.lower()
    f = tmp_path / "gateway.yaml"
    f.write_text(text)
    proc = subprocess.run(["cloud-init", "schema", "--config-file", str(f)], capture_output=True, text=True)
    assert proc.returncode == 0 and "Valid cloud-config" in proc.stdout, proc.stdout + proc.stderr
