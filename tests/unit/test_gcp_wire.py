"""The GCP provider on the wire: the real compute_v1 REST transport (anonymous credentials)
against requests-mock at https://compute.googleapis.com, so what is asserted is the HTTP request
GCE would receive, not a call on a mock."""

from __future__ import annotations

import json
from urllib.parse import parse_qs, urlparse

import pytest

pytest.importorskip("google.cloud.compute_v1")
requests_mock = pytest.importorskip("requests_mock")

from google.auth.credentials import AnonymousCredentials  # noqa: E402

from ccrp_cli.providers.base import CloneSpec  # noqa: E402
from ccrp_cli.providers.gcp.provider import GcpProvider  # noqa: E402
from ccrp_cli.providers.gcp import network  # noqa: E402
from ccrp_cli.providers.gcp.client import Clients  # noqa: E402
from ccrp_cli.retry import Backoff  # noqa: E402
from tests.contract.harness_gcp import PROJECT, REGION, ZONES, inventory  # noqa: E402

API = f"https://compute.googleapis.com/compute/v1/projects/{PROJECT}"
LINK = f"https://www.googleapis.com/compute/v1/projects/{PROJECT}"
ZONE = ZONES[0]
NAME = "ccrp-ct-cri-robot1"
USER_DATA = "#cloud-config\nhostname: cri-robot1\n"


def op(name: str, target: str) -> dict:
    return {"kind": "compute#operation", "name": name, "status": "DONE", "operationType": "insert", "targetLink": target}


def instance() -> dict:
    return {
        "kind": "compute#instance", "id": "4242", "name": NAME, "status": "PROVISIONING",
        "zone": f"{LINK}/zones/{ZONE}", "selfLink": f"{LINK}/zones/{ZONE}/instances/{NAME}", "canIpForward": True,
        "labels": {"ccrp-managed": "true", "ccrp-fleet": "ct", "ccrp-robot": "robot1", "ccrp-role": "clone"},
        "networkInterfaces": [{"network": f"{LINK}/global/networks/ccrp-ct-net", "networkIP": "10.90.0.10",
                               "accessConfigs": [{"name": "public", "natIP": "192.0.2.7"}]}],
    }


@pytest.fixture
def wire(tmp_path):
    inv = inventory()
    provider = GcpProvider(inv, tmp_path, clients=Clients.connect(credentials=AnonymousCredentials()))
    provider.client.backoff = Backoff(attempts=4, sleep=lambda s: None)
    with requests_mock.Mocker() as m:
        # Bootstrap finds the network, its subnetwork and the three rules as they should be.
        m.get(f"{API}/global/networks/ccrp-ct-net", json={
            "name": "ccrp-ct-net", "selfLink": f"{LINK}/global/networks/ccrp-ct-net",
            "description": "ccrp: ccrp-managed=true ccrp-fleet=ct ccrp-role=network"})
        m.get(f"{API}/regions/{REGION}/subnetworks", json={"items": [{
            "name": "ccrp-ct-common", "network": f"{LINK}/global/networks/ccrp-ct-net", "ipCidrRange": "10.90.0.0/24",
            "selfLink": f"{LINK}/regions/{REGION}/subnetworks/ccrp-ct-common"}]})
        for rule in network.firewall_rules(provider.client, f"{LINK}/global/networks/ccrp-ct-net"):
            m.get(f"{API}/global/firewalls/{rule.name}", json=json.loads(type(rule).to_json(rule)))
        m.get(f"{API}/aggregated/instances", json={"items": {}})
        # The clone's address is missing at first, reserved, then read back with its IP.
        address = f"{API}/regions/{REGION}/addresses/{NAME}"
        m.get(address, [
            {"status_code": 404, "json": {"error": {"code": 404, "message": "not found", "errors": [{"reason": "notFound"}]}}},
            {"status_code": 200, "json": {"name": NAME, "address": "192.0.2.7", "status": "RESERVED",
                                          "addressType": "EXTERNAL", "region": f"{LINK}/regions/{REGION}",
                                          "description": "ccrp: ccrp-managed=true ccrp-fleet=ct ccrp-role=address "
                                                         "ccrp-robot=robot1"}}])
        m.post(f"{API}/regions/{REGION}/addresses", json=op("operation-0", f"{LINK}/regions/{REGION}/addresses/{NAME}"))
        m.post(f"{API}/zones/{ZONE}/instances", [
            {"status_code": 429, "json": {"error": {"code": 429, "message": "Rate Limit Exceeded", "errors": [
                {"message": "Rate Limit Exceeded", "domain": "usageLimits", "reason": "rateLimitExceeded"}]}}},
            {"status_code": 200, "json": op("operation-1", f"{LINK}/zones/{ZONE}/instances/{NAME}")},
        ])
        m.get(f"{API}/zones/{ZONE}/instances/{NAME}", json=instance())
        m.get(f"{API}/global/routes/ccrp-ct-vpn-robot1", status_code=404,
              json={"error": {"code": 404, "message": "not found", "errors": [{"reason": "notFound"}]}})
        m.post(f"{API}/global/routes", json=op("operation-2", f"{LINK}/global/routes/ccrp-ct-vpn-robot1"))
        yield provider, m


def spec() -> CloneSpec:
    return CloneSpec(robot="robot1", hostname="cri-robot1", image="ccrp-ct-clone-golden", user_data=USER_DATA,
                     instance_id="ct-robot1-1", common_ip="10.90.0.10", vpn_subnet="10.80.1.0/24")


def test_run_instance_request_on_the_wire_and_a_429_retried_once(wire):
    provider, m = wire
    provider.bootstrap()
    assert [r.method for r in m.request_history].count("POST") == 0  # everything existed: nothing created

    record = provider.run_instance(spec())

    inserts = [r for r in m.request_history if r.method == "POST" and urlparse(r.url).path.endswith("/instances")]
    assert len(inserts) == 2  # the 429, then the one that succeeded
    assert urlparse(inserts[0].url).path == f"/compute/v1/projects/{PROJECT}/zones/{ZONE}/instances"
    ids = [parse_qs(urlparse(r.url).query)["requestId"] for r in inserts]
    assert ids[0] == ids[1] and len(ids[0]) == 1  # the retry is the same request to GCE
    body = inserts[1].json()
    assert body == inserts[0].json()
    assert body["name"] == NAME
    assert body["labels"] == {"ccrp-managed": "true", "ccrp-fleet": "ct", "ccrp-role": "clone", "ccrp-robot": "robot1"}
    assert body["canIpForward"] is True
    assert body["tags"] == {"items": ["ccrp-ct"]}
    assert body["machineType"] == f"zones/{ZONE}/machineTypes/e2-medium"
    metadata = {i["key"]: i["value"] for i in body["metadata"]["items"]}
    assert metadata["user-data"] == USER_DATA
    assert metadata["ssh-keys"].startswith("ccrp:ssh-ed25519 ") and metadata["ssh-keys"].endswith(" ccrp-ct")
    assert "startup-script" not in metadata  # a snapshot of the fleet: cloud-init is in it
    assert not any("PRIVATE KEY" in v for v in metadata.values())
    nic = body["networkInterfaces"][0]
    assert nic["networkIP"] == "10.90.0.10"
    assert nic["subnetwork"] == f"{LINK}/regions/{REGION}/subnetworks/ccrp-ct-common"
    # The reserved address, not an ephemeral IP (GCE would change that one at every stop/start).
    assert nic["accessConfigs"] == [{"name": "public", "type": "ONE_TO_ONE_NAT", "natIP": "192.0.2.7"}]
    reserved = [r for r in m.request_history if r.method == "POST" and urlparse(r.url).path.endswith("/addresses")]
    assert [r.json() for r in reserved] == [{"name": NAME, "addressType": "EXTERNAL", "description":
                                             "ccrp: ccrp-managed=true ccrp-fleet=ct ccrp-role=address ccrp-robot=robot1"}]
    assert body["disks"][0]["initializeParams"]["sourceImage"] == f"projects/{PROJECT}/global/images/ccrp-ct-clone-golden"
    assert "serviceAccounts" not in body  # nothing on a clone needs the GCP API

    routes = [r for r in m.request_history if r.method == "POST" and urlparse(r.url).path.endswith("/routes")]
    assert len(routes) == 1
    route = routes[0].json()
    assert route["destRange"] == "10.80.1.0/24"
    assert route["nextHopInstance"] == f"{LINK}/zones/{ZONE}/instances/{NAME}"
    assert route["network"] == f"{LINK}/global/networks/ccrp-ct-net"
    assert record.created and record.provider_id == "4242" and record.public_ip == "192.0.2.7"


def test_debian_image_gets_the_startup_script_that_runs_cloud_init(wire):
    """Debian's GCE images have no cloud-init: booted from one (the bake's builder, a bare clone), the
    instance gets a startup-script that installs cloud-init and runs it on the same user-data."""
    provider, m = wire
    provider.bootstrap()
    debian = "projects/debian-cloud/global/images/family/debian-12"
    provider.run_instance(spec().model_copy(update={"image": debian}))
    body = [r for r in m.request_history if r.method == "POST" and urlparse(r.url).path.endswith("/instances")][-1].json()
    metadata = {i["key"]: i["value"] for i in body["metadata"]["items"]}
    assert body["disks"][0]["initializeParams"]["sourceImage"] == debian
    assert metadata["user-data"] == USER_DATA and metadata["ssh-keys"].startswith("ccrp:ssh-ed25519 ")
    script = metadata["startup-script"]
    assert script.startswith("#!/bin/sh\n")
    assert "apt-get -q -y -o DPkg::Lock::Timeout=300 install cloud-init" in script
    assert "datasource_list: [ GCE, None ]" in script  # the datasource that reads `user-data`
    stages = [ln for ln in script.splitlines() if ln.startswith("cloud-init ")]
    assert stages == ["cloud-init init", "cloud-init modules --mode config", "cloud-init modules --mode final"]
    # Once cloud-init is installed, systemd runs it at every boot and the script steps aside.
    assert "[ -e /run/cloud-init/enabled ] && exit 0" in script
    assert "set_host_keys = false" in script  # the console's fingerprints stay the keys sshd serves


def test_request_id_depends_only_on_the_clone_and_zone(wire, tmp_path):
    provider, m = wire
    provider.bootstrap()
    provider.run_instance(spec())
    first = [r for r in m.request_history if r.method == "POST" and "/instances" in r.url][-1]
    # Another process (a re-run after a crash) sends the same id for the same clone and zone.
    other = GcpProvider(provider.inv, tmp_path / "other", clients=Clients.connect(credentials=AnonymousCredentials()))
    other.client.backoff = provider.client.backoff
    m.post(f"{API}/zones/{ZONE}/instances", json=op("operation-1", f"{LINK}/zones/{ZONE}/instances/{NAME}"))
    other.bootstrap()
    other.run_instance(spec())
    second = [r for r in m.request_history if r.method == "POST" and "/instances" in r.url][-1]
    assert parse_qs(urlparse(first.url).query)["requestId"] == parse_qs(urlparse(second.url).query)["requestId"]
