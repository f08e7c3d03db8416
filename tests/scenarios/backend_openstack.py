"""OpenStack for scenarios: the in-memory OpenStack served over real HTTP on 127.0.0.1, its
servers booted as containers (tests/fakes/cloudboot.py); ccrp reaches it through clouds.yaml and
OS_CLIENT_CONFIG_FILE with the real openstacksdk, as a user's shell would.

The fleet has an entry gateway (provider.entry: gateway) and the project one floating IP, fewer than
its robots: the gateway holds it, the clones none. The Debian-12 snapshot's builder takes that
floating IP while it bakes and gives it back. (The real OpenStack's end-to-end test runs a fleet
whose clones each have their own: tests/e2e/test_openstack_real.py.)"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from tests.fakes.cloudboot import CloudBoot
from tests.fakes.openstack_cloud import BOOT_IMAGE, FakeOpenStack
from tests.fakes.openstack_http import OpenStackHttp

from .backend import Backend, free_cidr, hello_software, inventory_text

CLOUD = "fakestack"


@contextmanager
def open_backend(tmp_path: Path, fleet: str, distro: str = "noetic"):
    with CloudBoot(progress=lambda msg: None) as boot:
        fake = FakeOpenStack(boot=boot)
        with OpenStackHttp(fake) as http:
            clouds = http.clouds_yaml(tmp_path, CLOUD)
            common = free_cidr("10.204.0.0/14")
            fake.max_fips = 1
            provider = (f"  kind: openstack\n  cloud: {CLOUD}\n  flavor: m1.small\n  image: {BOOT_IMAGE}\n"
                        f"  external_network: public\n  operator_cidr: {fake.fip_cidr}\n  zones: [az1, az2]\n"
                        "  entry: gateway\n")
            inv = tmp_path / "inventory.yaml"
            # ROS 1 only: OpenStack's bake builds the fleet's software on its builder (docs/workloads.md).
            software = hello_software(tmp_path) if distro == "noetic" else ""
            inv.write_text(inventory_text(fleet, provider, common, "10.85.0.0/16", distro) + software)
            yield Backend(kind="openstack", inventory=inv, home=tmp_path / "home",
                          env={"OS_CLIENT_CONFIG_FILE": str(clouds)}, owned=lambda: _owned(fake, fleet),
                          faults=_faults(fake), sim_network=fake.fip_network, labels=[f"ccrp-fake={boot.run}"],
                          nodes=["hello", "launched"] if software else [],
                          gateway=lambda: _delete_gateway(clouds, fleet))


def _delete_gateway(clouds: Path, fleet: str) -> str:
    """What an operator's `openstack server delete` of the fleet's gateway does, over the fake's API;
    its address, for the test to compare."""
    import openstack
    from openstack.config import OpenStackConfig

    conn = openstack.connection.Connection(config=OpenStackConfig(config_files=[str(clouds)]).get_one(cloud=CLOUD))
    try:
        [server] = [s for s in conn.compute.servers() if s.metadata.get("ccrp-fleet") == fleet
                    and s.metadata.get("ccrp-role") == "gateway"]
        address = next(a["addr"] for net in server.addresses.values() for a in net if a.get("OS-EXT-IPS:type") == "floating")
        conn.compute.delete_server(server)
        conn.compute.wait_for_delete(server, interval=1, wait=120)
        return address
    finally:
        conn.close()


def _owned(fake: FakeOpenStack, fleet: str) -> list[str]:
    """Everything the fake holds labelled with the fleet, snapshots (Glance images) aside."""
    tag = f"ccrp-fleet={fleet}"
    with fake.lock:
        found = [f"server {s['name']}" for s in fake.servers.values() if s["metadata"].get("ccrp-fleet") == fleet]
        for kind in ("networks", "subnets", "routers", "ports", "fips", "sgs"):
            found += [f"{kind} {r.get('name') or r['id']}" for r in getattr(fake, kind).values() if tag in r.get("tags", [])]
        found += [f"keypair {k}" for k in fake.keypairs if k == f"ccrp-{fleet}"]
    return found


def _faults(fake: FakeOpenStack) -> dict:
    from contextlib import contextmanager as cm

    @cm
    def quota():  # the project at its instance quota, as Nova's limits report: ccrp refuses up front
        before = fake.max_instances
        fake.max_instances = len(fake.servers)
        try:
            yield
        finally:
            fake.max_instances = before

    @cm
    def zone():  # the scheduler finds no host in az1: ccrp must fall back to az2
        fake.no_capacity.add("az1")
        try:
            yield
        finally:
            fake.no_capacity.discard("az1")

    @cm
    def storm():  # every third API call answered 429 or 503
        fake.throttle_fraction = 0.34
        try:
            yield
        finally:
            fake.throttle_fraction = 0.0

    return {"quota": quota, "zone": zone, "storm": storm}
