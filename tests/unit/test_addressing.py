import ipaddress

import pytest

from ccrp_cli.models.addressing import addresses, allocate, capacity
from ccrp_cli.errors import InputError
from ccrp_cli.loader import load_inventory
from tests.conftest import LAB


@pytest.fixture
def inv():
    return load_inventory(LAB)


def test_lab_plan(inv):
    a = addresses(inv, "nao1", 1)
    assert a.clone_host == "cri-nao1"
    assert a.vpn_subnet == ipaddress.IPv4Network("10.80.1.0/24")
    assert (str(a.clone_vpn_ip), str(a.robot_vpn_ip), str(a.common_ip)) == ("10.80.1.1", "10.80.1.2", "10.90.0.10")


def test_slots_are_stable_when_a_robot_leaves(inv):
    first = allocate(inv, ["nao1", "nao2", "turtlebot1"], {})
    assert first == {"nao1": 1, "nao2": 2, "turtlebot1": 3}
    # nao1 leaves, a new robot arrives: nobody else moves, the free slot is reused.
    again = allocate(inv, ["nao2", "turtlebot1", "robot1"], {"nao2": 2, "turtlebot1": 3})
    assert again == {"nao2": 2, "turtlebot1": 3, "robot1": 1}


def test_every_slot_is_distinct_and_inside_the_pools(inv):
    n = capacity(inv)
    assert n == min(255, 256 - 1 - 10)
    slots = allocate(inv, [f"robot{i}" for i in range(n)], {})
    plans = [addresses(inv, name, s) for name, s in slots.items()]
    assert len({p.vpn_subnet for p in plans}) == n and len({p.common_ip for p in plans}) == n
    for p in plans:
        assert p.vpn_subnet.subnet_of(inv.vpn.pool) and p.common_ip in inv.common.cidr
        assert p.common_ip != inv.common.cidr.broadcast_address


def test_exhausted_pool_is_an_input_error(inv):
    with pytest.raises(InputError, match="exhausted"):
        allocate(inv, [f"robot{i}" for i in range(capacity(inv) + 1)], {})
