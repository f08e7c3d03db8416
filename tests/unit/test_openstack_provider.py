"""OpenStack provider against the in-memory OpenStack (openstacksdk's own request building and
parsing, requests-mock transport): what only OpenStack has — ports with allowed address pairs,
floating IPs, Nova's scheduler faults, quota errors, no idempotency token."""

from __future__ import annotations

import base64
import json
import os
import sys

import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.providers.base import LABEL_FLEET, LABEL_ROBOT, Origin
from ccrp_cli.providers.openstack import network
from ccrp_cli.retry import ErrorClass
from tests.contract import specs
from tests.contract.harness_openstack import make_harness
from tests.fakes.openstack_cloud import BUILD_FAILED, NO_VALID_HOST

pytest.importorskip("openstack")


@pytest.fixture
def h(tmp_path):
    with make_harness(tmp_path) as harness:
        yield harness


def ports_of(h, robot):
    return [p for p in h.fake.ports.values() if f"{LABEL_ROBOT}={robot}" in p["tags"]]


def fips_of(h, robot):
    return [f for f in h.fake.fips.values() if f"{LABEL_ROBOT}={robot}" in f["tags"]]


def test_port_carries_fixed_ip_vpn_subnet_pair_and_fleet_security_group(h):
    spec = h.spec("robot1", 1)
    rec = h.provider.run_instance(spec)
    [port] = ports_of(h, "robot1")
    assert port["fixed_ips"][0]["ip_address"] == spec.common_ip == rec.common_ip
    assert port["allowed_address_pairs"] == [{"ip_address": spec.vpn_subnet}]
    assert port["device_id"] == rec.provider_id
    [sg] = [s for s in h.fake.sgs.values() if f"{LABEL_FLEET}=ct" in s["tags"]]
    assert port["security_groups"] == [sg["id"]]
    server = h.fake.servers[rec.provider_id]
    assert server["metadata"] == {"ccrp-managed": "true", "ccrp-fleet": "ct", "ccrp-role": "clone", "ccrp-robot": "robot1"}
    assert server["config_drive"] and server["key_name"] == "ccrp-ct"
    assert h.user_data_sent("robot1") == spec.user_data.encode()


def test_floating_ip_is_tagged_and_released_on_terminate(h):
    rec = h.provider.run_instance(h.spec("robot1", 1))
    [fip] = fips_of(h, "robot1")
    assert rec.public_ip == fip["floating_ip_address"]
    assert {"ccrp-managed=true", "ccrp-fleet=ct", "ccrp-robot=robot1"} <= set(fip["tags"])
    assert fip["port_id"] == ports_of(h, "robot1")[0]["id"]
    assert h.provider.terminate("robot1") is True
    assert fips_of(h, "robot1") == [] and ports_of(h, "robot1") == [] and h.instances_for("robot1") == 0
    assert h.provider.terminate("robot1") is False  # nothing left: still fine


def test_zone_fallback_after_no_valid_host(h):
    h.fake.no_capacity = {"az1"}
    rec = h.provider.run_instance(h.spec("robot1", 1))
    server = h.fake.servers[rec.provider_id]
    assert server["OS-EXT-AZ:availability_zone"] == "az2" and server["status"] == "ACTIVE"
    assert rec.created and h.instances_for("robot1") == 1  # the ERROR server in az1 was deleted
    assert len(ports_of(h, "robot1")) == 1  # the port was kept for the next zone
    assert h.api_calls()["POST compute:/v2.1/servers"] == 2


def test_no_capacity_anywhere_rolls_back_and_says_so(h):
    h.fake.no_capacity = {"az1", "az2"}
    before = h.owned_ids()
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(h.spec("robot1", 1))
    assert "no capacity in zones az1, az2" in err.value.one_line() and "provider.zones" in err.value.one_line()
    assert h.owned_ids() == before


def test_build_failures_on_every_host_are_not_called_a_lack_of_capacity(h):
    """Real Nova's fault when its compute hosts fail a build: the next zone is tried, and when all
    fail the user reads that the cloud could not build it, not "no capacity" (docs/openstack.md, 3)."""
    h.fake.build_fails = {"az1"}
    rec = h.provider.run_instance(h.spec("robot1", 1))
    assert h.fake.servers[rec.provider_id]["OS-EXT-AZ:availability_zone"] == "az2"
    h.fake.build_fails = {"az1", "az2"}
    before = h.owned_ids()
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(h.spec("robot2", 2))
    line = err.value.one_line()
    assert "could not build it in zones az1, az2" in line and "Exhausted all hosts" in line
    assert "no capacity" not in line and "nova-compute" in err.value.hint
    assert h.owned_ids() == before


def test_quota_is_one_line_error_with_hint_and_nothing_left(h):
    h.fake.max_instances = 0
    before = h.owned_ids()
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(h.spec("robot1", 1))
    line = err.value.one_line()
    assert "\n" not in line and "quota exceeded" in line and "Quota exceeded for instances" in line
    assert "openstack quota show" in err.value.hint
    assert h.owned_ids() == before
    assert h.api_calls()["POST compute:/v2.1/servers"] == 1  # REGION class: no retry, no other zone


def test_an_image_deleted_after_the_lookup_is_named_with_a_hint(h, monkeypatch):
    """A real Nova answers 400 "Can not find requested image" when the image left Glance between
    ccrp's lookup and the POST (docs/openstack.md, differences): ccrp names the image and hints."""
    spec = h.spec("robot1", 1)
    find = h.provider.client.find

    def find_then_delete(what, fn, name_or_id):
        found = find(what, fn, name_or_id)
        if what == "image":
            h.fake.images.pop(found.id)
        return found

    monkeypatch.setattr(h.provider.client, "find", find_then_delete)
    before = h.owned_ids()
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(spec)
    line = err.value.one_line()
    assert "\n" not in line and f"image {spec.image!r} not found" in line and "Can not find requested image" in line
    assert "ccrp snapshot list" in err.value.hint
    assert h.owned_ids() == before  # the port rolled back
    assert h.api_calls()["POST compute:/v2.1/servers"] == 1  # no retry, no other zone


def test_lookup_by_name_and_metadata_prevents_duplicates_after_a_crash(h, tmp_path):
    """ccrp created the server and died before saving state: the next run (a new process, a new
    provider) finds it by name + metadata instead of booting a second one."""
    first = h.provider.run_instance(h.spec("robot1", 1))
    again = h.new_provider(h.provider.inv, tmp_path / "store")
    rec = again.run_instance(h.spec("robot1", 1))
    assert rec.provider_id == first.provider_id and not rec.created
    assert rec.public_ip == first.public_ip
    assert h.instances_for("robot1") == 1 and len(ports_of(h, "robot1")) == 1 and len(fips_of(h, "robot1")) == 1


def test_a_port_left_by_a_crash_before_the_server_is_reused(h):
    spec = h.spec("robot1", 1)
    p = h.provider
    ext, net, subnet, sg = network.fleet_resources(p.client)
    p._port(spec, None, net, subnet, sg, [])  # the attempt died right after this
    rec = p.run_instance(spec)
    assert rec.created and len(ports_of(h, "robot1")) == 1 and rec.common_ip == spec.common_ip


def test_foreign_server_with_the_clone_name_is_neither_reused_nor_deleted(h):
    foreign = h.add_foreign()  # named ccrp-ct-cri-robot1, another fleet's metadata
    rec = h.provider.run_instance(h.spec("robot1", 1))
    assert rec.provider_id != foreign and rec.created
    h.provider.teardown()
    assert h.exists(foreign)
    with pytest.raises(CcrpError, match="not fleet 'ct'"):
        from ccrp_cli.providers.base import OwnedResource

        h.provider.delete_owned(OwnedResource(kind="instance", id=foreign))


def test_failure_after_server_rolls_back_server_port_and_keeps_reused(h):
    h.provider.run_instance(h.spec("robot1", 1))
    before = h.owned_ids()
    h.fail_create_after_instance("robot2")
    with pytest.raises(CcrpError, match="not reachable"):
        h.provider.run_instance(h.spec("robot2", 2))
    assert h.owned_ids() == before and h.instances_for("robot2") == 0


def test_teardown_in_dependency_order_keeps_snapshots(h):
    h.provider.run_instance(h.spec("robot1", 1))
    snap = h.provider.create_snapshot("robot1", "golden")
    removed = h.provider.teardown()
    kinds = [r.split()[0] for r in removed]
    assert kinds == ["instance", "floating_ip", "port", "router", "subnet", "network", "security_group", "key_pair"]
    assert h.owned_ids() == {snap.id}
    assert [s.id for s in h.provider.list_snapshots()] == [snap.id]
    h.provider.delete_snapshot(snap.id)
    assert h.owned_ids() == set()


def test_security_group_drops_a_stale_operator_rule(h):
    inv = h.provider.inv
    h.provider.inv = h.provider.client.inv = inv.model_copy(update={"provider": inv.provider.model_copy(update={"operator_cidr": "192.0.2.0/24"})})
    h.provider.settings = h.provider.client.settings = h.provider.inv.provider
    h.provider.bootstrap()
    assert h.public_ingress() == {("udp", 1194, "0.0.0.0/0"), ("tcp", 22, "192.0.2.0/24")}


def test_key_pair_with_another_key_is_not_taken_over(h):
    h.fake.keypairs["ccrp-ct"]["public_key"] = "ssh-ed25519 AAAAsomeoneelse x"
    with pytest.raises(CcrpError, match="exists .* with another key"):
        h.provider.bootstrap()


def test_user_data_over_the_limit_fails_before_any_call(h):
    calls = sum(h.api_calls().values())
    noise = base64.b64encode(os.urandom(300_000)).decode()  # does not gzip below the limit
    spec = h.spec("robot1", 1).model_copy(update={"user_data": "#cloud-config\n# " + noise})
    with pytest.raises(CcrpError, match="over openstack's limit"):
        h.provider.run_instance(spec)
    assert sum(h.api_calls().values()) == calls


def test_gc_lists_a_leak_and_deletes_it(h):
    leak = h.add_leak()
    found = [r for r in h.provider.list_owned() if r.id == leak]
    assert [(r.kind, r.robot) for r in found] == [("floating_ip", "ghost")]
    h.provider.delete_owned(found[0])
    assert not h.exists(leak)


def test_throttling_converges(h):
    h.throttle(0.3)
    rec = h.provider.run_instance(h.spec("robot1", 1))
    h.throttle(0)
    assert rec.created and h.instances_for("robot1") == 1


def test_classify_error():
    import requests
    from keystoneauth1 import exceptions as ksa
    from openstack import exceptions as exc

    from ccrp_cli.providers.openstack import errors

    def http(status, message):  # the exception openstacksdk raises for such a response
        response = requests.Response()
        response.status_code, response.reason = status, "x"
        response.headers["Content-Type"] = "application/json"
        response._content = json.dumps({"error": {"code": status, "message": message}}).encode()
        try:
            exc.raise_from_response(response)
        except exc.HttpException as err:
            return err

    assert errors.classify(http(429, "Rate limit")) is ErrorClass.RETRYABLE
    assert errors.classify(http(503, "Service Unavailable")) is ErrorClass.RETRYABLE
    assert errors.classify(ksa.ConnectFailure("reset")) is ErrorClass.RETRYABLE
    assert errors.classify(http(403, "Quota exceeded for instances")) is ErrorClass.REGION
    assert errors.classify(http(409, "Quota exceeded for resources: ['floatingip'].")) is ErrorClass.REGION
    assert errors.classify(errors.ServerFault(NO_VALID_HOST)) is ErrorClass.ZONE
    assert errors.classify(errors.ServerFault("Build of instance aborted: image broken")) is ErrorClass.FATAL
    assert errors.classify(errors.ServerFault(BUILD_FAILED.format(id="x"))) is ErrorClass.ZONE
    assert errors.classify(http(400, "Invalid key_name provided.")) is ErrorClass.FATAL
    assert errors.classify(http(401, "The request you have made requires authentication.")) is ErrorClass.FATAL


def test_console_output_and_credentials(h):
    h.provider.run_instance(h.spec("robot1", 1))
    assert "BEGIN SSH HOST KEY FINGERPRINTS" in h.provider.console_output("robot1")
    assert "authenticated" in h.provider.check_credentials()
    missing = [r.name for r in h.provider.inv.robots if r.name not in h.provider.query()]
    quotas = {q.name: q for q in h.provider.quotas(missing)}
    # Nova's limits and Neutron's floating IPs, their usage counted from the one server there is;
    # each clone not created yet takes a server, its flavor's 2 vCPUs and 4096 MB, a floating IP.
    assert {n: (q.limit, q.used, q.need(missing)) for n, q in quotas.items()} == {
        "instances": (100, 1, len(missing)), "cores": (200, 2, 2 * len(missing)),
        "ram (MB)": (409_600, 4096, 4096 * len(missing)), "floating-ips": (50, 1, len(missing))}


def test_wrong_credentials_are_one_line_with_a_hint_in_doctor_too(h, tmp_path):
    """A real Keystone's 401 reaches `ccrp doctor` (Connection.authorize) as a bare SDKException
    whose text only says "(HTTP 401)" (docs/openstack.md, differences): still the credentials' line."""
    h.fake.refuse_auth = True
    provider = h.new_provider(h.provider.inv, tmp_path / "other")
    for call in (provider.check_credentials, provider.bootstrap):
        with pytest.raises(CcrpError) as err:
            call()
        line = err.value.one_line()
        assert "\n" not in line and "refused the credentials" in line and "(HTTP 401)" in line, line
        assert "clouds.yaml" in err.value.hint


def test_missing_sdk_names_the_extra(monkeypatch, tmp_path):
    from ccrp_cli.providers.openstack.client import _connect

    monkeypatch.setitem(sys.modules, "openstack", None)
    with pytest.raises(CcrpError) as err:
        _connect("x")
    assert err.value.hint == "pip install 'ccrp[openstack]'"


def test_unknown_cloud_is_one_line(tmp_path, monkeypatch):
    from ccrp_cli.providers.openstack.client import _connect

    (tmp_path / "clouds.yaml").write_text("clouds: {}\n")
    monkeypatch.setenv("OS_CLIENT_CONFIG_FILE", str(tmp_path / "clouds.yaml"))
    with pytest.raises(CcrpError, match="cloud 'nowhere' is not configured"):
        _connect("nowhere")


def test_parallel_clones_get_their_own_servers_ports_and_addresses(h):
    from concurrent.futures import ThreadPoolExecutor

    robots = [f"robot{i}" for i in range(1, 6)]
    with ThreadPoolExecutor(max_workers=5) as pool:
        recs = list(pool.map(lambda ir: h.provider.run_instance(h.spec(ir[1], ir[0])), enumerate(robots, 1)))
    assert all(r.created for r in recs) and len({r.provider_id for r in recs}) == 5
    assert len({r.public_ip for r in recs}) == 5 and len({r.common_ip for r in recs}) == 5
    assert set(h.provider.query()) == set(robots)


def test_a_stopped_clone_is_started_and_an_errored_one_is_left_for_the_operator(h):
    first = h.provider.run_instance(h.spec("robot1", 1))
    h.fake.servers[first.provider_id]["status"] = "SHUTOFF"
    rec = h.provider.run_instance(h.spec("robot1", 1))
    assert rec.provider_id == first.provider_id and rec.status == "ACTIVE" and rec.origin is Origin.RESUMED
    assert first.origin is Origin.CREATED and h.provider.run_instance(h.spec("robot1", 1)).origin is Origin.REUSED
    h.fake.servers[first.provider_id].update(status="ERROR", fault={"message": "disk failure"})
    with pytest.raises(CcrpError, match="is in ERROR .disk failure"):
        h.provider.run_instance(h.spec("robot1", 1))
    assert h.exists(first.provider_id) and h.instances_for("robot1") == 1


def test_console_fingerprints_parse_as_ssh_pins(h):
    from ccrp_cli.transport.ssh import fingerprints_from_console

    h.provider.run_instance(h.spec("robot1", 1))
    assert len(fingerprints_from_console(h.provider.console_output("robot1"))) == 1


def test_a_named_network_is_used_not_routed_and_never_deleted(h, tmp_path):
    lab = h.fake.add("networks", {"name": "labnet"})
    h.fake._create_subnets({"network_id": lab["id"], "cidr": "10.90.0.0/24"})
    h.provider.teardown()  # the harness's own network goes first
    inv = h.provider.inv
    inv = inv.model_copy(update={"provider": inv.provider.model_copy(update={"network": "labnet"})})
    p = h.new_provider(inv, tmp_path / "store")
    p.bootstrap()
    assert not h.fake.routers  # the operator's network is routed already
    rec = p.run_instance(h.spec("robot1", 1))
    [port] = ports_of(h, "robot1")
    assert port["network_id"] == lab["id"]
    assert rec.public_ip
    p.teardown()
    assert lab["id"] in h.fake.networks and h.owned_ids() == set()


def test_what_rollback_cannot_delete_is_named_and_left_for_gc(h):
    h.fail_create_after_instance("robot1")
    h.fake.fail_next[("DELETE", "network:/v2.0/ports/{id}")] = (409, "Port is busy")
    with pytest.raises(CcrpError) as err:
        h.provider.run_instance(h.spec("robot1", 1))
    [port] = ports_of(h, "robot1")
    assert f"rollback left port {port['id']}" in err.value.one_line() and "not reachable" in err.value.one_line()
    assert h.instances_for("robot1") == 0  # the server went; only the port stayed
    [leak] = [r for r in h.provider.list_owned() if r.kind == "port"]
    h.provider.delete_owned(leak)
    assert ports_of(h, "robot1") == []


def test_neutron_without_tag_creation_gets_its_tags_after_the_post(h):
    """Zed's Neutron (Debian 12, scripts/openstack.sh) refuses `tags` in a POST body (400 "Attribute
    'tags' not allowed in POST"; the tag-creation extension came in 2023.1): each resource is created
    bare, then tagged with PUT .../tags, once the refusal was seen."""
    h.fake.tag_creation = False
    rec = h.provider.run_instance(h.spec("robot1", 1))
    [port] = ports_of(h, "robot1")
    [fip] = fips_of(h, "robot1")
    assert rec.public_ip == fip["floating_ip_address"] and port["device_id"] == rec.provider_id
    for store in (h.fake.networks, h.fake.subnets, h.fake.routers, h.fake.sgs):
        assert all(f"{LABEL_FLEET}=ct" in r["tags"] for r in store.values() if r["name"].startswith("ccrp-ct"))
    h.provider.run_instance(h.spec("robot2", 2))
    # the refusal is met once per provider, not once per resource
    assert h.fake.calls[("PUT", "network:/v2.0/ports/{id}/tags")] == 2
    assert h.provider.terminate("robot1") is True and ports_of(h, "robot1") == [] and fips_of(h, "robot1") == []
    # a port's POST is accepted with its tags dropped (201, tags []): a new run whose first
    # creation is a port (`ccrp clone create` on a bootstrapped fleet) still tags it
    h.provider.client._cache.pop("no-tag-creation")
    h.provider.run_instance(h.spec("robot3", 3))
    [port] = ports_of(h, "robot3")
    assert {"ccrp-managed=true", "ccrp-fleet=ct", "ccrp-robot=robot3"} <= set(port["tags"])


def test_a_resource_that_could_not_be_tagged_is_deleted_again(h):
    h.fake.tag_creation = False
    h.provider.bootstrap()
    h.fake.fail_next[("PUT", "network:/v2.0/ports/{id}/tags")] = (403, "tagging refused")
    with pytest.raises(CcrpError):
        h.provider.run_instance(h.spec("robot1", 1))
    assert [p for p in h.fake.ports.values() if not p["tags"] and p["device_owner"] != "network:router_interface"
            and p["device_owner"] != "network:router_gateway"] == []
    assert h.instances_for("robot1") == 0


def test_timeout_scale_is_one_unless_the_operator_says_the_cloud_emulates_the_cpu(h, monkeypatch):
    assert h.provider.timeout_scale("robot1") == 1
    monkeypatch.setenv("CCRP_OPENSTACK_TIMEOUT_SCALE", "6")
    assert h.provider.timeout_scale("robot1") == 6
    monkeypatch.setenv("CCRP_OPENSTACK_TIMEOUT_SCALE", "fast")
    assert h.provider.timeout_scale("robot1") == 1


def test_wait_ready_gives_a_slow_cloud_its_scale_times_longer(h, monkeypatch):
    """On the real single-node Nova (CPU emulated, CCRP_OPENSTACK_TIMEOUT_SCALE=6) two clones took
    more than the 300 s of wait_ready to finish cloud-init: the deadline is the scaled one."""
    import time as _time

    waits = []

    def keys_never_shown(robot, deadline):
        waits.append(deadline - _time.monotonic())
        raise CcrpError("stop here")
    monkeypatch.setattr(h.provider, "_wait_for_host_keys", keys_never_shown)
    monkeypatch.setenv("CCRP_OPENSTACK_TIMEOUT_SCALE", "6")
    with pytest.raises(CcrpError, match="stop here"):
        h.provider.wait_ready("robot1", timeout=300)
    assert 1790 < waits[0] <= 1800


@pytest.fixture
def gw(h, tmp_path):
    """The harness's cloud, with a fleet of provider.entry: gateway bootstrapped on it."""
    h.provider.teardown()
    inv = h.provider.inv
    inv = inv.model_copy(update={"provider": inv.provider.model_copy(update={"entry": "gateway"})})
    p = h.new_provider(inv, tmp_path / "gw-store")
    p.bootstrap()
    return p


def gateway_spec(h, p):
    return specs.gateway_spec(p.inv, h.spec("robot1", 1))


def test_behind_a_gateway_clones_get_no_floating_ip_and_the_gateway_keeps_the_fleets(h, gw):
    """provider.entry: gateway: the gateway's port is in a group of its own (the robots' ports from
    anywhere, SSH from the operator), with the fleet's floating IP; clones have none and their group
    lets the VPN port in from the common network only. The gateway's server deleted (by hand), the
    next one gets the same floating IP."""
    from ccrp_cli.models.addressing import capacity
    from ccrp_cli.providers.base import GATEWAY

    assert gw.gateway() is None
    clone = gw.run_instance(h.spec("robot1", 1))
    assert clone.public_ip is None and fips_of(h, "robot1") == []
    first = gw.run_instance(gateway_spec(h, gw))
    assert first.public_ip and first.common_ip == gateway_spec(h, gw).common_ip
    assert gw.gateway() == first.model_copy(update={"origin": None, "robot": GATEWAY})
    assert gw.query().keys() == {"robot1"}  # the gateway is not a clone
    groups = {s["name"]: {(r["protocol"], r["port_range_min"], r["port_range_max"], r["remote_ip_prefix"])
                          for r in s["security_group_rules"] if r["direction"] == "ingress"}
              for s in h.fake.sgs.values() if f"{LABEL_FLEET}=ct" in s["tags"]}
    vpn, operator = gw.inv.vpn, str(gw.settings.operator_cidr)
    assert groups["ccrp-ct-gateway"] == {(vpn.proto, vpn.port + 1, vpn.port + capacity(gw.inv), "0.0.0.0/0"),
                                         ("tcp", 22, 22, operator)}
    assert (vpn.proto, vpn.port, vpn.port, "0.0.0.0/0") not in groups["ccrp-ct-clones"]
    [port] = ports_of(h, GATEWAY)
    assert port["security_groups"] == [next(s["id"] for s in h.fake.sgs.values() if s["name"] == "ccrp-ct-gateway")]
    h.fake._delete_server(h.fake.servers[first.provider_id])  # `openstack server delete`: port and floating IP stay
    assert gw.gateway() is None
    again = gw.run_instance(gateway_spec(h, gw))
    assert again.created and again.provider_id != first.provider_id and again.public_ip == first.public_ip
    assert len(fips_of(h, GATEWAY)) == 1
    gw.teardown()
    assert h.owned_ids() == set()


def test_behind_a_gateway_the_quotas_count_it_once_and_no_floating_ip_per_clone(h, gw):
    h.fake.max_fips = 1
    fips = {q.name: q for q in gw.quotas(["robot1", "robot2", "robot3"])}["floating-ips"]
    instances = {q.name: q for q in gw.quotas(["robot1"])}["instances"]
    assert fips.need(["robot1", "robot2", "robot3"]) == 1 and instances.need(["robot1"]) == 2
    gw.run_instance(gateway_spec(h, gw))
    fips = {q.name: q for q in gw.quotas(["robot1", "robot2", "robot3"])}["floating-ips"]
    assert fips.need(["robot1", "robot2", "robot3"]) == 0 and fips.free == 0


def test_a_clone_kept_when_its_fleet_moves_behind_a_gateway_gives_its_floating_ip_back(h, tmp_path):
    rec = h.provider.run_instance(h.spec("robot1", 1))
    assert rec.public_ip and len(fips_of(h, "robot1")) == 1
    inv = h.provider.inv
    p = h.new_provider(inv.model_copy(update={"provider": inv.provider.model_copy(update={"entry": "gateway"})}),
                       h.provider.workdir)  # the same fleet store: the same operator key
    p.bootstrap()
    again = p.run_instance(h.spec("robot1", 1))
    assert again.origin is Origin.REUSED and again.provider_id == rec.provider_id
    assert again.public_ip is None and fips_of(h, "robot1") == []


def test_a_robots_lookup_asks_nova_for_that_robots_servers_only(h, monkeypatch):
    """Nova filters names by regex: robot1's lookup does not list robot2's server (nor any other's),
    so `fleet up` of N clones reads N servers, not N²."""
    one = h.provider.run_instance(h.spec("robot1", 1))
    two = h.provider.run_instance(h.spec("robot2", 2))
    assert [s.id for s in h.provider.client.servers("robot1")] == [one.provider_id]
    assert {s.id for s in h.provider.client.servers()} == {one.provider_id, two.provider_id}
    shown = []
    show = h.fake._show_server
    monkeypatch.setattr(h.fake, "_show_server", lambda server: shown.append(server["name"]) or show(server))
    h.provider.client.servers("robot1")
    assert shown == ["ccrp-ct-cri-robot1"]  # what Nova sent: one server
