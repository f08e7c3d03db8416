"""The provider contract: what every backend guarantees, driven only through the Provider
protocol and checked in the backend's fake (or real engine) through its harness."""

from __future__ import annotations

import gzip
from concurrent.futures import ThreadPoolExecutor


import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.ops.gc import find_leaks
from ccrp_cli.providers import info
from ccrp_cli.models.state import FleetState, RobotRecord
from ccrp_cli.providers.base import Ability, Origin
from ccrp_cli.ops.snapshots import BUILDER

from .harness import FLEET
from .specs import OPERATOR_CIDR, ROBOTS, gateway_spec


def create(harness, robot: str):
    return harness.provider.run_instance(harness.spec(robot, ROBOTS.index(robot) + 1))


def test_create_is_idempotent(harness):
    first = create(harness, "robot1")
    again = create(harness, "robot1")
    assert first.origin is Origin.CREATED and again.origin is Origin.REUSED
    assert first.created and not again.created
    assert again.provider_id == first.provider_id
    assert harness.instances_for("robot1") == 1
    assert harness.provider.query()["robot1"].provider_id == first.provider_id


def test_delete_touches_only_owned_resources(harness):
    foreign = harness.add_foreign()
    create(harness, "robot1")
    assert harness.provider.terminate("robot1") is True
    assert harness.instances_for("robot1") == 0
    assert harness.exists(foreign)
    assert harness.provider.terminate("robot1") is False  # nothing left of it: still no foreign harm
    create(harness, "robot2")
    harness.provider.teardown()
    assert harness.exists(foreign)
    assert harness.owned_ids() == set()


def test_failed_create_rolls_back_only_that_robot(harness):
    harness.fail_create_after_instance("robot3")
    failed = []
    for robot in ROBOTS:
        try:
            create(harness, robot)
        except CcrpError:
            failed.append(robot)
    assert failed == ["robot3"]
    assert harness.owned_ids("robot3") == set()
    for robot in ROBOTS:
        assert harness.instances_for(robot) == (0 if robot == "robot3" else 1)
    # The fault was one attempt's: the next run creates robot3 and leaves the others alone.
    assert create(harness, "robot3").created
    assert all(harness.instances_for(r) == 1 for r in ROBOTS)


def test_stop_keeps_the_clone_and_create_starts_it_again(harness):
    """`clone stop` asks the provider to stop a running clone and waits for STOPPED; the clone stays
    (same id), and the next create (what `clone start` and `fleet up` do) runs it again."""
    from ccrp_cli import retry
    from ccrp_cli.providers.base import CloneState

    first = create(harness, "robot1")
    create(harness, "robot2")
    stop(harness, "robot1")
    assert harness.provider.query()["robot2"].state is not CloneState.STOPPED  # only that robot's
    assert harness.provider.stop_instance("robot1") is False  # stopped already
    assert harness.provider.stop_instance("robot3") is False  # no clone at all
    again = create(harness, "robot1")
    assert again.provider_id == first.provider_id and again.origin is Origin.RESUMED  # started, not made
    retry.poll(lambda: (harness.provider.query()["robot1"].state is CloneState.RUNNING, None), timeout=120, interval=0.5)
    assert harness.instances_for("robot1") == 1
    # The robot's installed bundle dials the clone's public IP: stop/start must not change it.
    assert first.public_ip and harness.provider.query()["robot1"].public_ip == first.public_ip


def stop(harness, robot: str) -> None:
    from ccrp_cli import retry
    from ccrp_cli.providers.base import CloneState

    assert harness.provider.stop_instance(robot) is True
    state = retry.poll(lambda: ((s := harness.provider.query()[robot].state) is CloneState.STOPPED, s),
                       timeout=120, interval=0.5)
    assert state is CloneState.STOPPED


def test_snapshot_round_trip(harness):
    """A clone captured and deleted; a backend that captures only stopped clones (libvirt) says so
    and refuses a running one in one line."""
    create(harness, "robot1")
    if not info(harness.kind).snapshots_running:
        with pytest.raises(CcrpError, match="running"):
            harness.provider.create_snapshot("robot1", f"ccrp/{FLEET}-clone:robot1-contract")
        stop(harness, "robot1")
    snap = harness.provider.create_snapshot("robot1", f"ccrp/{FLEET}-clone:robot1-contract")
    assert snap.source == "robot1"
    assert snap.id in {s.id for s in harness.provider.list_snapshots()}
    assert harness.exists(snap.id)
    harness.provider.delete_snapshot(snap.id)
    assert snap.id not in {s.id for s in harness.provider.list_snapshots()}
    assert not harness.exists(snap.id)


def test_builder_is_labelled_as_such_and_never_taken_for_a_clone(harness):
    """`snapshot bake`'s builder: role "builder" in the cloud, not in query(); its snapshot is a
    build (no robot); terminating it leaves the clones alone."""
    if Ability.BAKE not in harness.provider.abilities:
        pytest.skip("snapshot build makes this backend's golden image, without a builder instance")
    create(harness, "robot1")
    spec = harness.spec("robot1", 1).model_copy(
        update={"robot": BUILDER, "hostname": "ccrp-builder", "role": "builder", "vpn_subnet": None,
                "instance_id": f"{FLEET}-builder-contract", "common_ip": harness.spec("robot2", 2).common_ip})
    assert harness.provider.run_instance(spec).origin is Origin.CREATED
    assert harness.provider.run_instance(spec).origin is Origin.REUSED  # idempotent as a clone's create
    assert harness.instance_roles(BUILDER) == ["builder"]
    assert set(harness.provider.query()) == {"robot1"}
    snap = harness.provider.create_snapshot(BUILDER, f"ccrp-{FLEET}-noetic-contract")
    assert snap.source == "build"
    assert harness.provider.terminate(BUILDER) is True
    assert harness.instances_for(BUILDER) == 0 and harness.owned_ids(BUILDER) == set()
    assert harness.instance_roles("robot1") == ["clone"]
    harness.provider.delete_snapshot(snap.id)


def test_gc_finds_and_deletes_an_injected_leak(harness):
    clone = create(harness, "robot1")
    state = FleetState(fleet=FLEET, robots={"robot1": RobotRecord(index=1, phase="ready", provider_id=clone.provider_id)})
    leak = harness.add_leak()
    owned = harness.provider.list_owned()
    assert leak in {r.id for r in owned}
    leaks = find_leaks(state, owned, harness.provider.list_snapshots())
    assert [r.id for r in leaks] == [leak]  # the clone, its extras and the network are known
    for r in leaks:
        harness.provider.delete_owned(r)
    assert not harness.exists(leak)
    assert harness.exists(clone.provider_id)


def test_public_ingress_is_vpn_and_operator_ssh_only(harness):
    create(harness, "robot1")
    vpn = harness.provider.inv.vpn
    expected = {(vpn.proto, vpn.port, "0.0.0.0/0")}
    if harness.provider.login_keys() is not None:  # a login over SSH, from the operator only (the
        expected.add(("tcp", 22, OPERATOR_CIDR))  # clouds); Docker and memory reach clones over their API
    assert harness.public_ingress() == expected


def test_user_data_carries_no_key_and_fits(harness):
    spec = harness.spec("robot1", 1)
    harness.provider.run_instance(spec)
    sent = harness.user_data_sent("robot1")
    limit, gzip_ok = info(harness.kind).user_data_limit, info(harness.kind).user_data_gzip
    assert len(sent) <= limit
    text = (gzip.decompress(sent) if sent[:2] == b"\x1f\x8b" else sent).decode()
    assert sent[:2] != b"\x1f\x8b" or gzip_ok
    assert text.startswith("#cloud-config") and f"hostname: {spec.hostname}" in text
    assert "PRIVATE KEY" not in text


def test_throttling_storm_creates_every_clone_once(harness):
    harness.throttle(1 / 3)
    with ThreadPoolExecutor(max_workers=len(ROBOTS)) as pool:
        records = list(pool.map(lambda r: create(harness, r), ROBOTS))
    assert all(r.created for r in records)
    assert len({r.provider_id for r in records}) == len(ROBOTS)
    harness.throttle(0)
    assert all(harness.instances_for(r) == 1 for r in ROBOTS)
    assert sum(harness.api_calls().values()) >= 3 * len(ROBOTS)


def test_an_entry_gateway_holds_the_fleets_one_public_address(harness, tmp_path):
    """Ability.ENTRY_GATEWAY: behind the gateway clones hold no public address; the gateway is not a
    clone; made again after its instance was deleted around ccrp, it has the same address; retired
    (terminate: the fleet went back to per-clone), its address goes with it; teardown leaves nothing."""
    from ccrp_cli.models.addressing import gateway_ip
    from ccrp_cli.providers.base import GATEWAY

    if Ability.ENTRY_GATEWAY not in harness.provider.abilities:
        pytest.skip(f"{harness.kind} makes no entry gateway")
    harness.provider.teardown()
    inv = harness.provider.inv
    gw = harness.new_provider(inv.model_copy(update={"provider": inv.provider.model_copy(update={"entry": "gateway"})}),
                              tmp_path / "gateway-store")
    gw.bootstrap()
    assert gw.gateway() is None
    spec = gateway_spec(gw.inv, harness.spec("robot1", 1))
    first = gw.run_instance(spec)
    assert first.origin is Origin.CREATED and first.public_ip and first.common_ip == str(gateway_ip(gw.inv))
    clones = [gw.run_instance(harness.spec(robot, i)) for i, robot in enumerate(ROBOTS[:2], start=1)]
    assert [c.public_ip for c in clones] == [None, None]
    assert gw.query().keys() == {"robot1", "robot2"}  # the gateway is not a clone
    assert gw.gateway().provider_id == first.provider_id
    harness.kill(first.provider_id)
    assert gw.gateway() is None
    again = gw.run_instance(spec)
    assert again.public_ip == first.public_ip and again.provider_id != first.provider_id
    assert gw.terminate(GATEWAY) is True
    assert gw.gateway() is None and all(first.public_ip not in (r.id, r.name) for r in gw.list_owned())
    assert [r for r in gw.list_owned() if r.robot == GATEWAY] == []  # its rules, routes, ports too
    gw.teardown()
    assert harness.owned_ids() == set() and gw.leftovers() == []


# -- contract v2: typed states, the calls every caller makes, declared abilities ------------------


def test_states_are_ccrp_words_and_every_declared_call_answers(harness):
    from ccrp_cli.providers.base import (Bake, CloneState, HostImages, LocalBuild, Provider, Quota, RobotAttach,
                                        Transport)

    created = create(harness, "robot1")
    rec = harness.provider.query()["robot1"]
    assert rec.state is CloneState.RUNNING, f"{harness.kind} maps {rec.status!r} to {rec.state}"
    assert created.state in (CloneState.PENDING, CloneState.RUNNING)
    assert harness.provider.abilities == info(harness.kind).abilities
    assert (Ability.LOCAL_BUILD in harness.provider.abilities) != (Ability.BAKE in harness.provider.abilities)
    for name in [n for n in dir(Provider) if not n.startswith("_")]:
        assert hasattr(harness.provider, name), f"{harness.kind} lacks {name}"
    # An ability is a promise of the calls that go with it.
    local = [n for n in dir(LocalBuild) if not n.startswith("_")]
    assert all(hasattr(harness.provider, n) for n in local) == (Ability.LOCAL_BUILD in harness.provider.abilities)
    if Ability.BAKE in harness.provider.abilities:
        assert all(hasattr(harness.provider, n) for n in dir(Bake) if not n.startswith("_"))
    for calls, ability in ((RobotAttach, Ability.ROBOT_ATTACH), (HostImages, Ability.HOST_IMAGES)):
        names = [n for n in dir(calls) if not n.startswith("_")]
        assert all(hasattr(harness.provider, n) for n in names) == (ability in harness.provider.abilities), ability
    assert all(hasattr(harness.provider.transport, n) for n in dir(Transport) if not n.startswith("_"))
    assert harness.provider.has_image("no-such-image-of-this-fleet") is False
    assert all(isinstance(q, Quota) and q.limit >= 0 for q in harness.provider.quotas())
    harness.provider.teardown()
    assert harness.provider.leftovers() == []
