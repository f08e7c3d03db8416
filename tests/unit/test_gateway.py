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


def test_gc_keeps_the_gateway_the_state_records_and_only_that():
    """`ccrp gc`: the gateway's instance, port and address (role GATEWAY, from its robot label) are the
    fleet's while the state records a gateway; with none recorded (a `fleet up` that died before
    saving it, so no robot has its address) they are leaks."""
    from ccrp_cli.models.state import FleetState, GatewayRecord
    from ccrp_cli.ops.gc import find_leaks
    from ccrp_cli.providers.base import GATEWAY, OwnedResource, Role, with_roles

    owned = with_roles([OwnedResource(kind="instance", id="i-gw", robot=GATEWAY),
                        OwnedResource(kind="floating_ip", id="f-gw", robot=GATEWAY),
                        OwnedResource(kind="security_group", id="sg-gw")], {"instance": Role.CLONE, "security_group": Role.BOOTSTRAP})
    assert [r.role for r in owned] == [Role.GATEWAY, Role.GATEWAY, Role.BOOTSTRAP]
    with_gateway = FleetState(fleet="f", gateway=GatewayRecord(provider_id="i-gw", public_ip="198.51.100.7"))
    assert find_leaks(with_gateway, owned, []) == []
    assert [r.id for r in find_leaks(FleetState(fleet="f"), owned, [])] == ["i-gw", "f-gw"]


class _Cloud:
    """What doctor asks of a backend with an entry gateway."""

    def __init__(self, found):
        self.found = found

    def gateway(self):
        return self.found


def test_doctor_says_whether_the_gateway_the_robots_dial_is_there(ccrp_home):
    from ccrp_cli.models.state import GatewayRecord
    from ccrp_cli.ops.doctor import FAIL, OK, WARN, _gateway
    from ccrp_cli.providers.base import GATEWAY, CloneRecord, CloneState
    from tests.conftest import LAB

    fleet = Fleet.open(LAB)
    running = CloneRecord(robot=GATEWAY, provider_id="gw-1", state=CloneState.RUNNING, status="ACTIVE", public_ip="198.51.100.7")
    assert _gateway(fleet, _Cloud(None)).status == OK  # none yet: fleet up makes it
    assert _gateway(fleet, _Cloud(running)).status == WARN  # there, but no state records it
    state = fleet.store.load_state()
    state.gateway = GatewayRecord(provider_id="gw-1", public_ip="198.51.100.7")
    fleet.store.save_state(state)
    assert _gateway(fleet, _Cloud(running)).status == OK
    gone = _gateway(fleet, _Cloud(None))
    assert gone.status == FAIL and "is gone" in gone.detail and "fleet up" in gone.hint
    moved = _gateway(fleet, _Cloud(running.model_copy(update={"public_ip": "198.51.100.8"})))
    assert moved.status == FAIL and "robots dial 198.51.100.7" in moved.detail


def test_fleet_plan_says_where_each_robot_will_dial_when_the_entry_changes(ccrp_home):
    """`fleet plan`'s endpoint: a fleet moving behind a gateway, or back, names the robots whose
    bundle dials the old place (they need their new one)."""
    from ccrp_cli.models.state import GatewayRecord
    from ccrp_cli.ops.reconcile import _endpoint_note
    from tests.conftest import LAB

    fleet = Fleet.open(LAB)
    state = fleet.load_allocated()
    state.robots["nao1"].public_endpoint = "172.30.0.10"
    assert _endpoint_note(fleet, state, "nao1") == "172.30.0.10"  # per-clone, as it was
    gw = fleet.inventory.model_copy(update={"provider": fleet.inventory.provider.model_copy(update={"entry": "gateway"})})
    fleet.inventory = gw
    port = entry_port(gw, state.robots["nao1"].index)
    assert _endpoint_note(fleet, state, "nao1") == f"the entry gateway's port {port} (was 172.30.0.10: new robot bundle)"
    state.gateway = GatewayRecord(provider_id="gw", public_ip="198.51.100.7")
    assert _endpoint_note(fleet, state, "nao1") == f"198.51.100.7:{port} (was 172.30.0.10: new robot bundle)"
    state.robots["nao1"].public_endpoint = f"198.51.100.7:{port}"
    assert _endpoint_note(fleet, state, "nao1") == f"198.51.100.7:{port}"
    fleet.inventory = gw.model_copy(update={"provider": gw.provider.model_copy(update={"entry": "per-clone"})})
    assert _endpoint_note(fleet, state, "nao1") == f"its clone's own address (was 198.51.100.7:{port}: new robot bundle)"
