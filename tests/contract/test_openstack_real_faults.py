"""The faults the real OpenStack (scripts/openstack.sh) can really cause, through ccrp's provider:
a project whose instance quota is 1, a flavor that does not exist, the clone's image deleted from
Glance under the fleet, wrong credentials. Each ends in one line with a hint (no traceback), and
nothing of the fleet is left in the cloud. Opt-in as the contract's real harness
(CCRP_E2E_OPENSTACK_REAL=1, `make contract-openstack-real`)."""

from __future__ import annotations

import copy
import os
from contextlib import contextmanager

import pytest
import yaml

from ccrp_cli.errors import CcrpError

from . import harness_openstack_real as real
from .specs import ROBOTS, clone_spec


@pytest.fixture
def cloud():
    if reason := real.gate():
        pytest.skip(reason)
    cloud, admin = real.connect(), real.connect(real.ADMIN_CLOUD)
    try:
        yield cloud, admin, real.tiny_root(cloud, f"ccrp-ct{real.RUN}-tiny")
    finally:
        cloud.close()
        admin.close()


def spec(provider, robot: str, image: str):
    return clone_spec(provider.inv, robot, ROBOTS.index(robot) + 1, image)


def one_line(err: CcrpError, *words: str, hint: str) -> None:
    """The error the user reads: one line with a hint, no traceback, saying `words`."""
    line = err.one_line()
    assert "\n" not in err.message and "Traceback" not in line, line
    assert err.hint and hint in err.hint, line
    for w in words:
        assert w in err.message, line


@contextmanager
def clouds_yaml(tmp_path, monkeypatch, **entries):
    """A clouds.yaml of its own (openstacksdk reads the first file found, OS_CLIENT_CONFIG_FILE
    first): `entries` are ccrp-aio's entry with changes to its auth ({name: {key: value}})."""
    from openstack.config.loader import OpenStackConfig

    base = OpenStackConfig().cloud_config["clouds"][real.CLOUD]
    clouds = {}
    for name, auth in entries.items():
        entry = copy.deepcopy(base)
        entry["auth"].update(auth)
        if "project_name" in auth:
            entry["auth"].pop("project_id", None)
        clouds[name] = entry
    path = tmp_path / "clouds.yaml"
    path.write_text(yaml.safe_dump({"clouds": clouds}))
    path.chmod(0o600)
    monkeypatch.setenv("OS_CLIENT_CONFIG_FILE", str(path))
    monkeypatch.setenv("OS_CLIENT_SECURE_FILE", str(tmp_path / "no-secure.yaml"))
    for key in [k for k in os.environ if k.startswith("OS_") and k not in ("OS_CLIENT_CONFIG_FILE", "OS_CLIENT_SECURE_FILE")]:
        monkeypatch.delenv(key)
    yield


def torn_down(provider, viewer) -> None:
    """fleet down, then nothing of the fleet in the cloud as `viewer` sees it."""
    provider.teardown()
    assert real.fleet_resources(viewer, provider.fleet) == {}


def test_a_flavor_that_does_not_exist(cloud, tmp_path):
    conn, _admin, image = cloud
    provider = real.make_provider(real.new_fleet(), tmp_path, flavor="ccrp-no-such-flavor")
    try:
        provider.bootstrap()
        with pytest.raises(CcrpError) as caught:
            provider.run_instance(spec(provider, "robot1", image))
        one_line(caught.value, "flavor 'ccrp-no-such-flavor' not found", hint="openstack flavor list")
        assert real.fleet_resources(conn, provider.fleet, "robot1") == {}  # its port was rolled back
        with pytest.raises(CcrpError) as caught:  # what `ccrp doctor` reads: the quotas of that flavor
            provider.quotas(["robot1"])
        one_line(caught.value, "ccrp-no-such-flavor", hint="openstack flavor list")
    finally:
        torn_down(provider, conn)


def test_the_image_deleted_under_the_fleet_before_a_create(cloud, tmp_path):
    """The fleet's image gone from Glance: before ccrp looks it up, and between ccrp's lookup and
    Nova's POST (a deletion racing the create)."""
    conn, admin, _image = cloud
    provider = real.make_provider(real.new_fleet(), tmp_path)
    harness = real.RealOpenStackHarness(provider, conn, admin, "")
    try:
        provider.bootstrap()
        gone = real.tiny_root(conn, f"ccrp-{provider.fleet}-doomed")
        conn.image.delete_image(gone)
        with pytest.raises(CcrpError) as caught:
            provider.run_instance(spec(provider, "robot1", gone))
        one_line(caught.value, f"image '{gone}' not found", hint="ccrp snapshot list")
        assert real.fleet_resources(conn, provider.fleet, "robot1") == {}

        racing = real.tiny_root(conn, f"ccrp-{provider.fleet}-racing")

        def delete_before_the_post(method, service, path):
            if method == "POST" and service == "compute" and path.rstrip("/").endswith("/servers"):
                conn.image.delete_image(racing)
        harness.before = delete_before_the_post
        with pytest.raises(CcrpError) as caught:
            provider.run_instance(spec(provider, "robot2", racing))
        harness.before = None
        one_line(caught.value, racing, hint="ccrp snapshot list")
        assert real.fleet_resources(conn, provider.fleet, "robot2") == {}
    finally:
        harness.before = None
        torn_down(provider, conn)


def test_wrong_credentials(cloud, tmp_path, monkeypatch):
    conn, _admin, image = cloud
    fleet = real.new_fleet()
    with clouds_yaml(tmp_path, monkeypatch, **{"ccrp-aio-wrong": {"password": "not-the-password"}}):
        provider = real.make_provider(fleet, tmp_path, cloud="ccrp-aio-wrong")
        for call in (provider.bootstrap, provider.check_credentials,
                     lambda: provider.run_instance(spec(provider, "robot1", image))):
            with pytest.raises(CcrpError) as caught:
                call()
            one_line(caught.value, "refused the credentials", hint="clouds.yaml")
    assert real.fleet_resources(conn, fleet) == {}


@pytest.fixture
def quota_of_one(cloud, tmp_path, monkeypatch):
    """A project of its own whose instance quota is 1 (never project ccrp's), user ccrp a member,
    the run's images shared with it; the project and everything in it deleted at the end."""
    conn, admin, image = cloud
    name = f"ccrp-ct{real.RUN}-quota1"
    project = admin.identity.create_project(name=name, domain_id="default",
                                            description="ccrp contract: instance quota of 1 (deleted at the end)")
    try:
        admin.grant_role("member", user=conn.current_user_id, project=project.id)
        admin.set_compute_quotas(project.id, instances=1)
        with clouds_yaml(tmp_path, monkeypatch, **{"ccrp-aio-quota1": {"project_name": name}}):
            mine = real.connect("ccrp-aio-quota1")
            try:
                for image_id in [image, *real.shared_ids()]:
                    conn.image.add_member(image_id, member=project.id)
                    mine.image.update_member(project.id, image_id, status="accepted")
                yield mine, image
            finally:
                _empty_project(admin, project.id)
                for image_id in [image, *real.shared_ids()]:
                    conn.image.remove_member(project.id, image_id, ignore_missing=True)
                mine.close()
    finally:
        admin.identity.delete_project(project.id, ignore_missing=True)


def _empty_project(admin, project_id: str) -> None:
    """What a failed test may have left in the quota project (admin listings of that project only)."""
    for server in admin.compute.servers(all_projects=True, project_id=project_id):
        admin.compute.delete_server(server, ignore_missing=True)
        admin.compute.wait_for_delete(server, interval=real.POLL, wait=300)
    for fip in admin.network.ips(project_id=project_id):
        admin.network.delete_ip(fip, ignore_missing=True)
    for router in admin.network.routers(project_id=project_id):
        for port in admin.network.ports(device_id=router.id, device_owner="network:router_interface"):
            admin.network.remove_interface_from_router(router, port_id=port.id)
        admin.network.delete_router(router, ignore_missing=True)
    for port in admin.network.ports(project_id=project_id):
        admin.network.delete_port(port, ignore_missing=True)
    for net in admin.network.networks(project_id=project_id):
        admin.network.delete_network(net, ignore_missing=True)
    for sg in admin.network.security_groups(project_id=project_id):  # Neutron's `default` group too
        admin.network.delete_security_group(sg, ignore_missing=True)


def test_a_quota_of_one_instance_and_two_clones(quota_of_one, tmp_path):
    from ccrp_cli.ops import quotas

    mine, image = quota_of_one
    provider = real.make_provider(real.new_fleet(), tmp_path, cloud="ccrp-aio-quota1")
    try:
        provider.bootstrap()
        # Before any create (`fleet up`, `ccrp doctor`): the real Nova's limits refuse the second clone.
        with pytest.raises(quotas.QuotaError) as caught:
            quotas.check(provider, ["robot1", "robot2"], progress=lambda _m: None)
        one_line(caught.value, "instances", "1 free, this needs 2", hint="at most 1 of the 2 new clones")
        # Asked anyway (another fleet took the last one meanwhile): Nova's own refusal, in one line.
        assert provider.run_instance(spec(provider, "robot1", image)).created
        with pytest.raises(CcrpError) as caught:
            provider.run_instance(spec(provider, "robot2", image))
        one_line(caught.value, "quota exceeded", hint="quota")
        assert real.fleet_resources(mine, provider.fleet, "robot2") == {}
        assert set(provider.query()) == {"robot1"}
    finally:
        torn_down(provider, mine)
