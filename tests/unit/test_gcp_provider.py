"""GCP provider behaviour on the autospecced fake project (tests/contract/harness_gcp.py):
zone fallback, quota errors, firewall contents, VPN routes, rollback, idempotency details."""

from __future__ import annotations

import subprocess
import sys

import pytest

pytest.importorskip("google.cloud.compute_v1")

from google.api_core import exceptions  # noqa: E402

from ccrp_cli.errors import CcrpError  # noqa: E402
from ccrp_cli.providers.base import CloneSpec, Origin  # noqa: E402
from ccrp_cli.providers.gcp.errors import classify  # noqa: E402
from ccrp_cli.retry import ErrorClass  # noqa: E402
from ccrp_cli.providers.gcp.ownership import tail  # noqa: E402
from tests.contract.harness_gcp import PUBLIC_IMAGE, ZONES, FakeProject, GcpHarness, inventory  # noqa: E402


def spec(robot: str, index: int, **over) -> CloneSpec:
    fields = dict(robot=robot, hostname=f"cri-{robot}", image=PUBLIC_IMAGE,
                  user_data=f"#cloud-config\nhostname: cri-{robot}\n", instance_id=f"ct-{robot}-{index}",
                  common_ip=f"10.90.0.{9 + index}", vpn_subnet=f"10.80.{index}.0/24")
    return CloneSpec(**(fields | over))


@pytest.fixture
def h(tmp_path) -> GcpHarness:
    return GcpHarness(tmp_path)


def inserts(h: GcpHarness) -> list:
    return [call.kwargs["request"] for call in h.fake.clients.instances.insert.call_args_list]


def test_zone_fallback_on_resource_pool_exhausted(h):
    h.fake.exhausted.add(ZONES[0])
    record = h.provider.run_instance(spec("robot1", 1))
    assert record.created
    assert [r.zone for r in inserts(h)] == ZONES[:2]
    assert [zone for zone, _name in h.fake.instances] == [ZONES[1]]
    # Each zone has its own request id: a stock-out's failed operation is not replayed elsewhere.
    assert len({r.request_id for r in inserts(h)}) == 2


def test_every_zone_exhausted_is_one_line(h):
    h.fake.exhausted.update(ZONES)
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(spec("robot1", 1))
    line = err.value.one_line()
    assert "no capacity in zones europe-west2-a, europe-west2-b" in line and "hint: add zones" in line
    assert "\n" not in line and h.fake.instances == {}


def test_quota_is_a_region_error_with_a_hint_and_no_zone_hopping(tmp_path):
    h = GcpHarness(tmp_path, FakeProject(cpu_quota=2))
    h.provider.run_instance(spec("robot1", 1))
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(spec("robot2", 2))
    line = err.value.one_line()
    assert line.startswith("clone ccrp-ct-cri-robot2: GCE quota exceeded in europe-west2")
    assert "Quota 'CPUS' exceeded" in line and "hint: request more quota for europe-west2" in line
    assert "\n" not in line
    assert [r.zone for r in inserts(h) if r.instance_resource.name.endswith("robot2")] == [ZONES[0]]
    assert h.instances_for("robot2") == 0
    # Five robots in the inventory, one clone up: 2 vCPUs used, 8 more needed, 2 allowed.
    missing = ["robot2", "robot3", "robot4", "robot5"]
    assert ("CPUS", 2.0, 2.0, 8.0) in [(q.name, q.limit, q.used, q.need(missing)) for q in h.provider.quotas(missing)]


def test_firewall_rules_are_the_vpn_port_operator_ssh_and_the_common_network(h):
    h.provider.bootstrap()
    rules = {r.name: r for r in h.fake.firewalls.values()}
    assert set(rules) == {"ccrp-ct-vpn", "ccrp-ct-ssh", "ccrp-ct-common"}
    shape = {name: (r.direction, [(a.I_p_protocol, list(a.ports)) for a in r.allowed], list(r.source_ranges),
                    list(r.target_tags)) for name, r in rules.items()}
    assert shape == {
        "ccrp-ct-vpn": ("INGRESS", [("udp", ["1194"])], ["0.0.0.0/0"], ["ccrp-ct"]),
        "ccrp-ct-ssh": ("INGRESS", [("tcp", ["22"])], ["198.51.100.0/24"], ["ccrp-ct"]),
        "ccrp-ct-common": ("INGRESS", [("all", [])], ["10.90.0.0/24"], ["ccrp-ct"]),
    }
    assert all(r.description == "ccrp: ccrp-managed=true ccrp-fleet=ct ccrp-role=network" for r in rules.values())
    h.provider.run_instance(spec("robot1", 1))
    (inst,) = h.fake.instances.values()
    assert list(inst.tags.items) == ["ccrp-ct"]  # the rules apply to clones through this tag


def test_changed_vpn_port_updates_the_rule_and_nothing_else(tmp_path):
    fake = FakeProject()
    GcpHarness(tmp_path, fake).provider.bootstrap()
    inv = inventory()
    inv.vpn.port = 443
    h = GcpHarness(tmp_path, fake, inv)
    h.provider.bootstrap()
    assert h.fake.firewalls["ccrp-ct-vpn"].allowed[0].ports == ["443"]
    assert [c.kwargs["firewall"] for c in fake.clients.firewalls.update.call_args_list] == ["ccrp-ct-vpn"]
    assert fake.calls["networks.insert"] == 1 and fake.calls["subnetworks.insert"] == 1


def test_route_follows_the_clone(h):
    record = h.provider.run_instance(spec("robot1", 1))
    route = h.fake.routes["ccrp-ct-vpn-robot1"]
    (inst,) = h.fake.instances.values()
    assert inst.can_ip_forward and route.next_hop_instance == inst.self_link
    assert route.dest_range == "10.80.1.0/24" and route.network == inst.network_interfaces[0].network
    assert route.description == "ccrp: ccrp-managed=true ccrp-fleet=ct ccrp-role=route ccrp-robot=robot1"
    assert record.common_ip == "10.90.0.10"
    assert h.provider.terminate("robot1") is True
    assert h.fake.routes == {} and h.fake.instances == {}


def test_stale_route_of_an_earlier_clone_is_replaced(h):
    h.provider.run_instance(spec("robot1", 1))
    h.fake.instances.clear()  # the clone vanished behind ccrp's back; its route stayed
    h.provider.run_instance(spec("robot1", 1, vpn_subnet="10.80.9.0/24"))
    (inst,) = h.fake.instances.values()
    assert h.fake.routes["ccrp-ct-vpn-robot1"].next_hop_instance == inst.self_link
    assert h.fake.routes["ccrp-ct-vpn-robot1"].dest_range == "10.80.9.0/24"


def test_rollback_deletes_only_what_the_attempt_created(h):
    h.provider.run_instance(spec("robot1", 1))
    kept = dict(h.fake.routes), {k: v.id for k, v in h.fake.instances.items()}
    h.fail_create_after_instance("robot2")
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(spec("robot2", 2))
    assert err.value.one_line().startswith("clone ccrp-ct-cri-robot2: BadRequest")
    assert h.instances_for("robot2") == 0 and h.owned_ids("robot2") == set()
    assert (dict(h.fake.routes), {k: v.id for k, v in h.fake.instances.items()}) == kept


def test_reused_clone_survives_a_failed_route(h):
    first = h.provider.run_instance(spec("robot1", 1))
    h.fake.routes.clear()
    h.fail_create_after_instance("robot1")
    with pytest.raises(CcrpError):
        h.provider.run_instance(spec("robot1", 1))
    assert h.instances_for("robot1") == 1  # not this attempt's: never rolled back
    again = h.provider.run_instance(spec("robot1", 1))
    assert not again.created and again.provider_id == first.provider_id
    assert "ccrp-ct-vpn-robot1" in h.fake.routes


def test_throttled_insert_keeps_its_request_id(h):
    h.provider.bootstrap()
    h.throttle(0.6)
    h.provider.run_instance(spec("robot1", 1))
    h.throttle(0)
    sent = inserts(h)  # every attempt, the throttled ones included
    assert len(sent) >= 2 and len({r.request_id for r in sent}) == 1
    assert h.instances_for("robot1") == 1


def test_recreate_within_the_request_id_window(h):
    """GCE replays a remembered requestId's operation without creating anything: a clone deleted
    and created again within the hour must still come back."""
    first = h.provider.run_instance(spec("robot1", 1))
    assert h.provider.terminate("robot1")
    again = h.provider.run_instance(spec("robot1", 1))
    assert again.created and again.provider_id != first.provider_id
    assert h.instances_for("robot1") == 1
    ids = [r.request_id for r in inserts(h)]
    assert ids[0] == ids[1] != ids[2]


def test_recreate_several_times_within_the_request_id_window(h):
    """Each re-creation within the hour leaves one more remembered operation on the clone's chain of
    request ids: the third creation meets two earlier operations before GCE creates anything (it
    used to stop after one and fail with the instance not found)."""
    for _ in range(2):
        h.provider.run_instance(spec("robot1", 1))
        assert h.provider.terminate("robot1")
    third = h.provider.run_instance(spec("robot1", 1))
    assert third.created and h.instances_for("robot1") == 1
    ids = [r.request_id for r in inserts(h)]
    assert len(ids) == 1 + 2 + 3 and len(set(ids)) == 3  # the same chain of ids every time: deterministic
    assert ids[:1] == ids[1:2] == ids[3:4] and ids[2] == ids[4]


def test_stopped_clone_is_started_and_reused(h):
    first = h.provider.run_instance(spec("robot1", 1))
    (inst,) = h.fake.instances.values()
    inst.status = "TERMINATED"
    again = h.provider.run_instance(spec("robot1", 1))
    assert again.origin is Origin.RESUMED and again.provider_id == first.provider_id and again.status == "RUNNING"
    assert h.provider.run_instance(spec("robot1", 1)).origin is Origin.REUSED  # running: left as it was


def test_foreign_instance_with_the_clone_name_is_refused_and_untouched(h):
    foreign = h.add_foreign()
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(spec("foreign", 1))
    assert "name taken" in err.value.one_line()
    assert h.provider.terminate("foreign") is False
    h.provider.teardown()
    assert h.exists(foreign)


def test_named_network_is_used_not_owned(tmp_path):
    from google.cloud import compute_v1 as c

    fake = FakeProject()
    fake.clients.networks.insert(network_resource=c.Network(name="lab", auto_create_subnetworks=False), project="p")
    fake.clients.subnetworks.insert(project="p", region="europe-west2", subnetwork_resource=c.Subnetwork(
        name="lab-eu", network="global/networks/lab", ip_cidr_range="10.90.0.0/16"))
    h = GcpHarness(tmp_path, fake, inventory(network="lab"))
    h.provider.run_instance(spec("robot1", 1))
    (inst,) = fake.instances.values()
    assert inst.network_interfaces[0].subnetwork.endswith("/subnetworks/lab-eu")
    assert set(fake.firewalls) == {"ccrp-ct-vpn", "ccrp-ct-ssh", "ccrp-ct-common"}
    h.provider.teardown()
    assert set(fake.networks) == {"lab"} and set(fake.subnetworks) == {"lab-eu"} and fake.firewalls == {}


def test_missing_named_network_is_one_line(tmp_path):
    h = GcpHarness(tmp_path, inv=inventory(network="nope"))
    with pytest.raises(CcrpError, match="network 'nope' not found in project ccrp-test"):
        h.provider.bootstrap()


def test_oversized_user_data_fails_before_any_call(h):
    with pytest.raises(CcrpError, match="over gcp's limit of 262144 bytes"):
        h.provider.run_instance(spec("robot1", 1, user_data="#cloud-config\n" + "x" * 262_144))
    assert sum(h.api_calls().values()) == 0


def test_teardown_order_and_snapshots_kept(h):
    for i, robot in enumerate(["robot1", "robot2"], 1):
        h.provider.run_instance(spec(robot, i))
    snap = h.provider.create_snapshot("robot1", "ccrp/ct-clone:robot1-20260101")
    assert snap.name == "ccrp-ct-clone-robot1-20260101"
    removed = h.provider.teardown()  # the fake refuses to delete a network still in use
    assert [r.split()[0] for r in removed] == (["route"] * 2 + ["instance"] * 2 + ["address"] * 2 + ["firewall"] * 3
                                               + ["subnet", "network"])
    assert h.fake.addresses == {}
    assert h.owned_ids() == {snap.id} and h.provider.leftovers() == []


@pytest.mark.parametrize("exc, expected", [
    (exceptions.TooManyRequests("Rate Limit Exceeded"), ErrorClass.RETRYABLE),
    (exceptions.ServiceUnavailable("Backend Error"), ErrorClass.RETRYABLE),
    (exceptions.InternalServerError("oops"), ErrorClass.RETRYABLE),
    (exceptions.Forbidden("Rate Limit Exceeded", errors=[{"reason": "rateLimitExceeded"}]), ErrorClass.RETRYABLE),
    (exceptions.Forbidden("Quota 'CPUS' exceeded", errors=[{"reason": "quotaExceeded"}]), ErrorClass.REGION),
    (exceptions.ServiceUnavailable("SERVICE UNAVAILABLE", errors=[{"code": "ZONE_RESOURCE_POOL_EXHAUSTED"}]),
     ErrorClass.ZONE),
    (exceptions.BadRequest("The zone 'projects/p/zones/z' does not have enough resources available"), ErrorClass.ZONE),
    (exceptions.ServiceUnavailable("A e2-medium VM instance is currently unavailable in the europe-west2-a zone."),
     ErrorClass.ZONE),
    (exceptions.Forbidden("Quota exceeded", errors=[{"reason": "CONCURRENT_OPERATIONS_QUOTA_EXCEEDED"}]),
     ErrorClass.RETRYABLE),
    (exceptions.BadRequest("The resource 'projects/p/global/networks/n' is not ready",
                           errors=[{"reason": "resourceNotReady"}]), ErrorClass.RETRYABLE),
    (exceptions.ServiceUnavailable("no capacity", errors=[{"code": "REGION_RESOURCE_POOL_EXHAUSTED"}]), ErrorClass.REGION),
    (exceptions.Forbidden("Required 'compute.instances.create' permission"), ErrorClass.FATAL),
    (exceptions.BadRequest("Invalid value for field 'resource.machineType'"), ErrorClass.FATAL),
    (exceptions.NotFound("The resource was not found"), ErrorClass.FATAL),
])
def test_classify(exc, expected):
    assert classify(exc) is expected


def test_transport_errors_are_retried():
    import requests

    assert classify(requests.exceptions.ConnectionError("reset")) is ErrorClass.RETRYABLE


def test_no_credentials_is_one_line(tmp_path, monkeypatch):
    import google.auth
    from google.auth.exceptions import DefaultCredentialsError

    from ccrp_cli.providers.gcp.provider import GcpProvider

    def no_adc(**_kw):
        raise DefaultCredentialsError("Your default credentials were not found. To set up ADC, see ...")

    monkeypatch.setattr(google.auth, "default", no_adc)
    provider = GcpProvider(inventory(), tmp_path)  # constructing needs no credentials yet
    with pytest.raises(CcrpError) as err:
        provider.check_credentials()
    assert "no Google Cloud credentials found" in err.value.one_line()
    assert "gcloud auth application-default login" in err.value.one_line()


def test_check_credentials_reads_the_region(h):
    assert h.provider.check_credentials() == "project ccrp-test, region europe-west2: UP"


def test_missing_sdk_names_the_extra(tmp_path, monkeypatch):
    import google.cloud

    from ccrp_cli.providers.gcp.provider import GcpProvider

    monkeypatch.delattr(google.cloud, "compute_v1")
    monkeypatch.setitem(sys.modules, "google.cloud.compute_v1", None)  # as if never installed
    with pytest.raises(CcrpError) as err:
        GcpProvider(inventory(), tmp_path)
    assert "pip install 'ccrp[gcp]'" in err.value.one_line()


def test_importing_the_backend_does_not_import_the_sdk():
    code = ("import sys, ccrp_cli.providers.gcp; "
            "assert 'google.cloud.compute_v1' not in sys.modules and 'google.auth' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_snapshot_builder_is_not_a_clone(h):
    """`snapshot bake` boots a builder (role builder, no VPN subnet), images it and deletes it."""
    builder = spec("snapshot-builder", 1, role="builder", vpn_subnet=None, common_ip="10.90.0.9")
    h.provider.run_instance(builder)
    (inst,) = h.fake.instances.values()
    assert inst.name == "ccrp-ct-builder-snapshot-builder" and inst.labels["ccrp-role"] == "builder"
    assert h.provider.query() == {} and h.fake.routes == {}
    assert "booting ccrp-ct-builder-snapshot-builder" in h.provider.console_output("snapshot-builder")
    snap = h.provider.create_snapshot("snapshot-builder", "ccrp-ct-noetic-20260101")
    assert snap.source == "build" and "ccrp-robot" not in h.fake.images[snap.name].labels
    assert h.provider.terminate("snapshot-builder") is True and h.fake.instances == {}


def _operation(*steps):
    """An operation as compute_v1 returns it, RUNNING at first; each poll takes the next step:
    an Operation to report or an exception to raise."""
    from google.cloud import compute_v1 as c

    from tests.contract.harness_gcp import FakeOperation

    polls = []

    def refresh(retry=None):
        step = steps[min(len(polls), len(steps) - 1)]
        polls.append(step)
        if isinstance(step, Exception):
            raise step
        return step

    running = c.Operation(name="operation-1", status=c.Operation.Status.RUNNING)
    return FakeOperation.make(refresh, lambda: None, running), polls


def test_failed_polls_of_an_operation_are_retried(h):
    from google.cloud import compute_v1 as c

    done = c.Operation(name="operation-1", status=c.Operation.Status.DONE)
    op, polls = _operation(exceptions.ServiceUnavailable("Backend Error"), exceptions.TooManyRequests("slow down"), done)
    h.provider.client.wait(op, "create instance cri-robot1")
    assert len(polls) == 3


def test_an_operations_own_error_is_not_polled_again(h):
    from google.cloud import compute_v1 as c

    failed = c.Operation(name="operation-1", status=c.Operation.Status.DONE, http_error_status_code=503,
                         http_error_message="SERVICE UNAVAILABLE",
                         error=c.Error(errors=[c.Errors(code="ZONE_RESOURCE_POOL_EXHAUSTED", message="stock-out")]))
    op, polls = _operation(failed)
    with pytest.raises(exceptions.GoogleAPICallError) as err:
        h.provider.client.wait(op, "create instance cri-robot1")
    assert len(polls) == 1
    assert classify(err.value) is ErrorClass.ZONE  # the caller moves to the next zone


# -- the reserved external address ----------------------------------------------------------------
def _nat(h: GcpHarness, robot: str = "robot1") -> str:
    return h._clone(robot).network_interfaces[0].access_configs[0].nat_i_p


def test_fake_gives_an_ephemeral_ip_a_new_address_at_every_start(h):
    """What the reserved address is for: without one, GCE (and the fake) changes the IP."""
    from google.cloud import compute_v1 as c

    h.provider.run_instance(spec("robot1", 1))
    (zone, name), inst = next(iter(h.fake.instances.items()))
    where = dict(project="p", zone=zone, instance=name, network_interface="nic0")
    h.fake.clients.instances.delete_access_config(access_config="public", **where)
    h.fake.clients.instances.add_access_config(
        access_config_resource=c.AccessConfig(name="public", type_="ONE_TO_ONE_NAT"), **where)
    before = _nat(h)
    h.fake.clients.instances.stop(project="p", zone=zone, instance=name)
    assert _nat(h) == ""  # released at stop
    h.fake.clients.instances.start(project="p", zone=zone, instance=name)
    assert _nat(h) not in ("", before)


def test_clone_keeps_its_reserved_address_across_stop_start_and_loses_it_with_the_clone(h):
    first = h.provider.run_instance(spec("robot1", 1))
    address = h.fake.clients.addresses.get(project="p", region="europe-west2", address="ccrp-ct-cri-robot1")
    assert first.public_ip == address.address == _nat(h)
    assert address.status == "IN_USE" and address.users == [h._clone("robot1").self_link]
    assert address.description == "ccrp: ccrp-managed=true ccrp-fleet=ct ccrp-role=address ccrp-robot=robot1"
    assert h.provider.stop_instance("robot1")
    assert h.provider.query()["robot1"].public_ip == first.public_ip  # a stopped clone keeps it
    again = h.provider.run_instance(spec("robot1", 1))
    assert not again.created and again.public_ip == first.public_ip
    assert len(h.fake.addresses) == 1  # reused, not reserved again
    assert {r.kind for r in h.provider.list_owned() if r.robot == "robot1"} == {"instance", "address", "route"}
    assert h.provider.terminate("robot1") is True
    assert h.fake.addresses == {} and "address" not in {r.kind for r in h.provider.list_owned()}


def test_every_zone_exhausted_releases_the_address_it_reserved(h):
    h.provider.run_instance(spec("robot1", 1))
    h.fake.exhausted.update(ZONES)
    with pytest.raises(CcrpError, match="no capacity"):
        h.provider.run_instance(spec("robot2", 2))
    assert set(h.fake.addresses) == {"ccrp-ct-cri-robot1"}


def test_address_quota_is_one_line_creates_nothing_and_doctor_counts_it(tmp_path):
    h = GcpHarness(tmp_path, FakeProject(address_quota=1))
    h.provider.run_instance(spec("robot1", 1))
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(spec("robot2", 2))
    line = err.value.one_line()
    assert "GCE quota exceeded in europe-west2" in line and "Quota 'STATIC_ADDRESSES' exceeded" in line
    assert h.owned_ids("robot2") == set() and set(h.fake.addresses) == {"ccrp-ct-cri-robot1"}
    # Five robots, one address reserved: four more needed, one allowed.
    missing = ["robot2", "robot3", "robot4", "robot5"]
    assert ("STATIC_ADDRESSES", 1.0, 1.0, 4.0) in [(q.name, q.limit, q.used, q.need(missing))
                                                    for q in h.provider.quotas(missing)]


def test_clone_of_an_earlier_ccrp_keeps_its_ephemeral_ip_as_its_reserved_address(h):
    """A clone created before ccrp reserved addresses runs at an ephemeral IP, which the robot's
    bundle dials: the next run promotes that IP instead of moving the clone to a new one."""
    first = h.provider.run_instance(spec("robot1", 1))
    del h.fake.addresses["ccrp-ct-cri-robot1"]  # as if never reserved: the IP is the instance's own
    again = h.provider.run_instance(spec("robot1", 1))
    assert again.public_ip == first.public_ip
    address = h.fake.addresses["ccrp-ct-cri-robot1"]
    assert address.address == first.public_ip and address.status == "IN_USE"


def test_reused_clone_at_another_ip_is_moved_back_to_its_reserved_address(h):
    from google.cloud import compute_v1 as c

    first = h.provider.run_instance(spec("robot1", 1))
    (zone, name), _inst = next(iter(h.fake.instances.items()))
    where = dict(project="p", zone=zone, instance=name, network_interface="nic0")
    h.fake.clients.instances.delete_access_config(access_config="public", **where)
    h.fake.clients.instances.add_access_config(
        access_config_resource=c.AccessConfig(name="public", type_="ONE_TO_ONE_NAT"), **where)
    assert _nat(h) != first.public_ip
    again = h.provider.run_instance(spec("robot1", 1))
    assert again.public_ip == first.public_ip == _nat(h)


def test_foreign_address_with_the_clone_name_is_refused_and_kept(h):
    from google.cloud import compute_v1 as c

    h.fake.clients.addresses.insert(project="p", region="europe-west2",
                                    address_resource=c.Address(name="ccrp-ct-cri-robot1", description="mine"))
    with pytest.raises(CcrpError, match="address ccrp-ct-cri-robot1 exists in europe-west2 but is not ccrp's"):
        h.provider.run_instance(spec("robot1", 1))
    assert h.instances_for("robot1") == 0
    h.provider.teardown()
    assert set(h.fake.addresses) == {"ccrp-ct-cri-robot1"}


def test_gc_finds_an_address_left_by_a_crash_and_releases_it(h):
    from ccrp_cli.ops.gc import find_leaks
    from ccrp_cli.models.state import FleetState, RobotRecord

    clone = h.provider.run_instance(spec("robot1", 1))
    h.provider.run_instance(spec("robot2", 2))
    h.fake.instances.pop(next(k for k, i in h.fake.instances.items() if i.labels["ccrp-robot"] == "robot2"))
    state = FleetState(fleet="ct", robots={"robot1": RobotRecord(index=1, phase="ready", provider_id=clone.provider_id)})
    leaks = find_leaks(state, h.provider.list_owned(), [])
    assert {(r.kind, r.name) for r in leaks} == {("address", "ccrp-ct-cri-robot2"), ("route", "ccrp-ct-vpn-robot2")}
    for r in leaks:
        h.provider.delete_owned(r)
    assert set(h.fake.addresses) == {"ccrp-ct-cri-robot1"}


def test_address_insert_whose_reply_was_lost_is_used_and_rolled_back_as_this_attempts(h):
    """The insert went through but its reply was lost (503): the retry meets 409 alreadyExists, the
    address is used, and released again when no zone can create the clone."""
    real = h.fake.clients.addresses.insert.side_effect
    lost = []

    def insert_then_lose_the_reply(*args, **kwargs):
        op = real(*args, **kwargs)
        if not lost:
            lost.append(op)
            raise exceptions.ServiceUnavailable("Backend Error", errors=[{"reason": "backendError"}])
        return op

    h.fake.clients.addresses.insert.side_effect = insert_then_lose_the_reply
    h.fake.exhausted.update(ZONES)
    with pytest.raises(CcrpError, match="no capacity"):
        h.provider.run_instance(spec("robot1", 1))
    assert h.fake.clients.addresses.insert.call_count == 2 and h.fake.addresses == {}
    h.fake.exhausted.clear()
    record = h.provider.run_instance(spec("robot1", 1, instance_id="ct-robot1-2"))  # not the failed requestIds
    assert record.public_ip == h.fake.addresses["ccrp-ct-cri-robot1"].address


# -- the entry gateway (provider.entry: gateway, GCP's default) -----------------------------------
def gateway_harness(tmp_path, fake: FakeProject | None = None) -> GcpHarness:
    h = GcpHarness(tmp_path, fake, inventory(entry="gateway"))
    h.provider.bootstrap()
    return h


def gateway_spec(h: GcpHarness) -> CloneSpec:
    from tests.contract import specs

    return specs.gateway_spec(h.inv, spec("robot1", 1))


def test_gcp_fleets_are_behind_a_gateway_unless_the_inventory_says_per_clone():
    from tests.contract import specs

    settings = {"kind": "gcp", "project": "p", "region": "europe-west2", "zones": ["europe-west2-a"],
                "operator_cidr": specs.OPERATOR_CIDR}
    assert specs.inventory(settings).provider.entry == "gateway"
    assert specs.inventory(settings | {"entry": "per-clone"}).provider.entry == "per-clone"


def test_behind_a_gateway_clones_have_no_external_ip_and_the_gateway_the_fleets_one(tmp_path):
    """The gateway: its own tag and firewall rules (the robots' ports from anywhere, SSH from the
    operator), the fleet's one reserved address, and the clones' way out (a route 0.0.0.0/0 for the
    clones' tag through it, above GCE's default route). Clones: no access config, no address, the
    VPN port and SSH from the common network only. The gateway deleted by hand, the next one gets
    the same address and the route follows it."""
    from ccrp_cli.models.addressing import capacity
    from ccrp_cli.providers.base import GATEWAY

    h = gateway_harness(tmp_path)
    vpn, common = h.inv.vpn, str(h.inv.common.cidr)
    shape = {r.name: ([(a.I_p_protocol, list(a.ports)) for a in r.allowed], list(r.source_ranges), list(r.target_tags))
             for r in h.fake.firewalls.values()}
    assert shape == {
        "ccrp-ct-vpn": ([("udp", ["1194"])], [common], ["ccrp-ct"]),
        "ccrp-ct-ssh": ([("tcp", ["22"])], [common], ["ccrp-ct"]),
        "ccrp-ct-common": ([("all", [])], [common], ["ccrp-ct", "ccrp-ct-gateway"]),
        "ccrp-ct-gateway-robots": ([("udp", [f"{vpn.port + 1}-{vpn.port + capacity(h.inv)}"])], ["0.0.0.0/0"],
                                   ["ccrp-ct-gateway"]),
        "ccrp-ct-gateway-ssh": ([("tcp", ["22"])], ["198.51.100.0/24"], ["ccrp-ct-gateway"]),
    }
    assert h.public_ingress() == {("udp", p, "0.0.0.0/0") for p in range(vpn.port + 1, vpn.port + capacity(h.inv) + 1)} \
        | {("tcp", 22, "198.51.100.0/24")}  # the robots' ports and the operator's SSH, on the gateway only
    clone = h.provider.run_instance(spec("robot1", 1))
    inst = h._clone("robot1")
    assert clone.public_ip is None and list(inst.network_interfaces[0].access_configs) == []
    assert list(inst.tags.items) == ["ccrp-ct"] and h.fake.addresses == {}
    assert h.provider.gateway() is None
    first = h.provider.run_instance(gateway_spec(h))
    gw = h._clone(GATEWAY)
    assert first.public_ip and first.common_ip == gateway_spec(h).common_ip
    assert gw.can_ip_forward and list(gw.tags.items) == ["ccrp-ct-gateway"] and gw.labels["ccrp-role"] == "gateway"
    assert tail(gw.machine_type) == "e2-micro"  # provider.gateway_machine_type: it only forwards packets
    assert [a.address for a in h.fake.addresses.values()] == [first.public_ip]
    assert h.provider.gateway() == first.model_copy(update={"origin": None})
    assert h.provider.query().keys() == {"robot1"}  # the gateway is not a clone
    route = h.fake.routes["ccrp-ct-egress"]
    assert (route.dest_range, route.priority, list(route.tags), route.next_hop_instance) == \
        ("0.0.0.0/0", 900, ["ccrp-ct"], gw.self_link)
    h.fake.clients.instances.delete(project="p", zone=tail(gw.zone), instance=gw.name)  # by hand: address, route stay
    assert h.provider.gateway() is None and len(h.fake.addresses) == 1
    again = h.provider.run_instance(gateway_spec(h))
    assert again.created and again.provider_id != first.provider_id and again.public_ip == first.public_ip
    assert h.fake.routes["ccrp-ct-egress"].next_hop_instance == h._clone(GATEWAY).self_link  # re-pointed
    assert len(h.fake.addresses) == 1
    h.provider.teardown()
    assert h.owned_ids() == set()


def test_the_gateways_resources_are_its_role_for_gc_and_go_with_it(tmp_path):
    """What the gateway holds (its instance, the fleet's address, its route and firewall rules) is
    Role.GATEWAY, which gc keeps while the state records the gateway; terminate (a fleet back to
    per clone) deletes the instance, its route, its firewall rules and the address."""
    from ccrp_cli.providers.base import GATEWAY, Role

    h = gateway_harness(tmp_path)
    h.provider.run_instance(spec("robot1", 1))
    h.provider.run_instance(gateway_spec(h))
    roles = {(r.kind, r.name): r.role for r in h.provider.list_owned()}
    assert {k for k, role in roles.items() if role is Role.GATEWAY} == {
        ("instance", "ccrp-ct-gateway-entry-gateway"), ("address", "ccrp-ct-gateway-entry-gateway"),
        ("route", "ccrp-ct-egress"), ("firewall", "ccrp-ct-gateway-robots"), ("firewall", "ccrp-ct-gateway-ssh")}
    assert roles[("instance", "ccrp-ct-cri-robot1")] is Role.CLONE
    assert h.provider.terminate(GATEWAY) is True
    assert h.fake.addresses == {} and "ccrp-ct-egress" not in h.fake.routes and h._clone(GATEWAY) is None
    assert set(h.fake.firewalls) == {"ccrp-ct-vpn", "ccrp-ct-ssh", "ccrp-ct-common"}


def test_behind_a_gateway_the_quotas_count_it_once_and_no_address_per_clone(tmp_path):
    """A new project's 8 addresses: a fleet of any size needs one (the gateway's), held once; its
    vCPUs (of provider.gateway_machine_type) are counted beside the clones'."""
    h = GcpHarness(tmp_path, None, inventory(entry="gateway", machine_type="e2-standard-4"))
    robots = [f"robot{i}" for i in range(1, 101)]
    need = {q.name: q.need(robots) for q in h.provider.quotas(robots)}
    assert need == {"CPUS": 4 * 100 + 2, "IN_USE_ADDRESSES": 1, "STATIC_ADDRESSES": 1}
    h.provider.run_instance(gateway_spec(h))
    need = {q.name: q.need(robots) for q in h.provider.quotas(robots)}
    assert need == {"CPUS": 4 * 100, "IN_USE_ADDRESSES": 0, "STATIC_ADDRESSES": 0}


def test_a_gateway_made_again_needs_no_new_address(tmp_path):
    h = gateway_harness(tmp_path, FakeProject(address_quota=1, in_use_address_quota=1))
    h.provider.run_instance(gateway_spec(h))
    gw = next(i for i in h.fake.instances.values() if i.labels["ccrp-role"] == "gateway")
    h.fake.clients.instances.delete(project="p", zone=tail(gw.zone), instance=gw.name)
    need = {q.name: q.need(["robot1"]) for q in h.provider.quotas(["robot1"])}
    assert need["STATIC_ADDRESSES"] == 0 and need["IN_USE_ADDRESSES"] == 1  # reserved already; held by no instance
    assert h.provider.run_instance(gateway_spec(h)).public_ip


def test_a_clone_kept_when_its_fleet_moves_behind_a_gateway_gives_its_address_back(tmp_path):
    fake = FakeProject()
    per_clone = GcpHarness(tmp_path, fake)
    rec = per_clone.provider.run_instance(spec("robot1", 1))
    assert rec.public_ip and set(fake.addresses) == {"ccrp-ct-cri-robot1"}
    h = gateway_harness(tmp_path, fake)
    again = h.provider.run_instance(spec("robot1", 1))
    assert again.origin is Origin.REUSED and again.provider_id == rec.provider_id
    assert again.public_ip is None and fake.addresses == {}
    assert list(h._clone("robot1").network_interfaces[0].access_configs) == []


def test_the_fakes_route_insert_checks_its_fields_as_gce_does(tmp_path):
    from google.cloud import compute_v1 as c

    h = gateway_harness(tmp_path)
    h.provider.run_instance(gateway_spec(h))
    hop = h.fake.routes["ccrp-ct-egress"]
    for bad in (dict(dest_range="0.0.0.0/33"), dict(priority=70000), dict(tags=["Not A Tag"])):
        route = c.Route(**(dict(name="ccrp-ct-x", network=hop.network, dest_range="0.0.0.0/0", priority=900,
                                next_hop_instance=hop.next_hop_instance) | bad))
        with pytest.raises(exceptions.BadRequest):
            h.fake.clients.routes.insert(project="p", route_resource=route)
    assert set(h.fake.routes) == {"ccrp-ct-egress"}
