"""The contract harness on an in-memory OpenStack (tests/fakes/openstack_cloud.py) behind
requests-mock, with the Keystone catalog of openstacksdk's own ConnectionFixture: the provider's
real `openstack.connect(cloud=...)` reads a clouds.yaml written here and every request it sends
is built and parsed by openstacksdk itself. Nothing leaves the process (unmatched URLs fail)."""

from __future__ import annotations

import base64
import ipaddress
import os
from collections import Counter
from contextlib import contextmanager

from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE

from ..fakes.openstack_cloud import FakeOpenStack
from .harness import FLEET
from .specs import FAST, OPERATOR_CIDR, clone_spec, inventory

CLOUD = "ccrp-fake"
BASE_IMAGE = "ubuntu-20.04"
OWNED_TAGS = {f"{LABEL_MANAGED}=true", f"{LABEL_FLEET}={FLEET}"}


def _owned_labels(labels: dict, robot: str | None) -> bool:
    return (labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == FLEET
            and (robot is None or labels.get(LABEL_ROBOT) == robot))


def public_ingress(groups, common) -> set[tuple[str, int, str]]:
    """(protocol, port, source) of each ingress rule of the security groups (Neutron's dicts) that
    admits traffic from outside the common network."""
    rules = set()
    for sg in groups:
        for r in sg["security_group_rules"]:
            if r["direction"] != "ingress":
                continue
            prefix = r["remote_ip_prefix"] or ("0.0.0.0/0" if not r["remote_group_id"] else None)
            if prefix and not (ipaddress.ip_network(prefix).version == 4
                               and ipaddress.ip_network(prefix).subnet_of(common)):
                rules.add((r["protocol"] or "any", r["port_range_min"] or -1, prefix))
    return rules


class OpenStackHarness:
    kind = "openstack"

    def __init__(self, fake: FakeOpenStack, provider) -> None:
        self.fake, self.provider = fake, provider

    def new_provider(self, inv, workdir):
        """An OpenStackProvider (a fresh process, as far as ccrp knows) wired to this fake."""
        from ccrp_cli.providers.openstack.provider import OpenStackProvider

        provider = OpenStackProvider(inv, workdir)
        self.fake.attach(provider.client.conn)
        provider.client.backoff = FAST
        provider.client.poll_interval = 0.01
        return provider

    # -- knobs ----------------------------------------------------------------------------------
    def spec(self, robot: str, index: int):
        return clone_spec(self.provider.inv, robot, index, BASE_IMAGE)

    def fail_create_after_instance(self, robot: str) -> None:
        self.fake.fail_fip_for.add(robot)  # the floating IP request after the server was created fails

    def throttle(self, fraction: float) -> None:
        self.fake.throttle_fraction = fraction

    def delay(self, seconds: float) -> None:
        self.fake.delay_s = seconds

    def api_calls(self) -> Counter:
        return Counter({f"{method} {op}": n for (method, op), n in self.fake.calls.items()})

    # -- the fake's contents, read around the provider ------------------------------------------
    def _servers(self, robot: str | None = None) -> list[dict]:
        return [s for s in self.fake.servers.values() if _owned_labels(s["metadata"], robot)]

    def owned_ids(self, robot: str | None = None) -> set[str]:
        f = self.fake
        want = OWNED_TAGS | ({f"{LABEL_ROBOT}={robot}"} if robot else set())
        ids = {s["id"] for s in self._servers(robot)}
        for store in (f.networks, f.subnets, f.routers, f.ports, f.fips, f.sgs):
            ids |= {r["id"] for r in store.values() if want <= set(r["tags"])}
        ids |= {i["id"] for i in f.images.values() if _owned_labels(i, robot)}
        if robot is None:  # Nova key pairs carry no labels: the fleet's is known by name
            ids |= {name for name in f.keypairs if name == f"ccrp-{FLEET}"}
        return ids

    def add_foreign(self) -> str:
        # Named exactly like robot1's clone and labelled, but for another fleet.
        image = next(i for i in self.fake.images.values() if i["name"] == BASE_IMAGE)
        created = self.fake._create_server({
            "name": f"ccrp-{FLEET}-cri-robot1", "imageRef": image["id"], "flavorRef": next(iter(self.fake.flavors)),
            "metadata": {LABEL_MANAGED: "true", LABEL_FLEET: "other", LABEL_ROLE: "clone", LABEL_ROBOT: "robot1"}})
        return created["id"]

    def add_leak(self) -> str:
        # A floating IP left behind by a crash between allocation and attachment: idle floating
        # IPs cost money and use quota, the classic OpenStack leak.
        ext = next(n for n in self.fake.networks.values() if n["router:external"])
        tags = [f"{LABEL_MANAGED}=true", f"{LABEL_FLEET}={FLEET}", f"{LABEL_ROLE}=clone", f"{LABEL_ROBOT}=ghost"]
        return self.fake._create_fips({"floating_network_id": ext["id"], "tags": tags})["id"]

    def kill(self, provider_id: str) -> None:
        self.fake._delete_server(self.fake.servers[provider_id])

    def exists(self, resource_id: str) -> bool:
        f = self.fake
        stores = (f.servers, f.networks, f.subnets, f.routers, f.ports, f.fips, f.sgs, f.images, f.keypairs)
        return any(resource_id in store for store in stores)

    def public_ingress(self) -> set[tuple[str, int, str]]:
        groups = [sg for sg in self.fake.sgs.values() if OWNED_TAGS <= set(sg["tags"])]
        return public_ingress(groups, self.provider.inv.common.cidr)

    def user_data_sent(self, robot: str) -> bytes:
        return base64.b64decode(self._servers(robot)[0]["user_data"])

    def instance_roles(self, robot: str) -> list[str]:
        return [s["metadata"].get(LABEL_ROLE, "") for s in self._servers(robot)]

    def instances_for(self, robot: str) -> int:
        return len(self._servers(robot))


@contextmanager
def _isolated_env(**values: str):
    """openstacksdk reads its configuration from the environment: point it at the fake only."""
    keys = [k for k in os.environ if k.startswith("OS_")] + list(values)
    saved = {k: os.environ.get(k) for k in keys}
    for k in keys:
        os.environ.pop(k, None)
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextmanager
def make_harness(tmp_path):
    fake = FakeOpenStack()
    config = fake.clouds_yaml(tmp_path, CLOUD)
    inv = inventory({"kind": "openstack", "cloud": CLOUD, "flavor": "m1.small", "external_network": "public",
                     "operator_cidr": OPERATOR_CIDR, "zones": ["az1", "az2"]})
    env = {"OS_CLIENT_CONFIG_FILE": str(config), "OS_CLIENT_SECURE_FILE": str(tmp_path / "no-secure.yaml")}
    with _isolated_env(**env):
        h = OpenStackHarness(fake, None)
        h.provider = h.new_provider(inv, tmp_path / "store")
        h.provider.bootstrap()
        yield h
    # The fake lives in memory only, reached through the provider's own session: nothing to stop.
