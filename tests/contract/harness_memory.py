"""The contract harness on the memory backend (tests/memory_backend, tests only): registered with
its one line, on an empty memory cloud, which the harness reads and rigs directly, around the
provider."""

from __future__ import annotations

from collections import Counter
from contextlib import contextmanager

from ccrp_cli.providers import register, unregister
from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, owner_labels

from tests.memory_backend import INFO, cloud

from .harness import FLEET
from .specs import FAST, clone_spec, inventory

class MemoryHarness:
    kind = "memory"

    def __init__(self, provider, fake: cloud.MemoryCloud) -> None:
        self.provider, self.cloud = provider, fake
        fake.add("image", INFO.bake_base, {})  # the cloud's own image: no labels, never the fleet's

    def _owned(self, kind: str | None = None, robot: str | None = None) -> list[cloud.Resource]:
        labels = {LABEL_MANAGED: "true", LABEL_FLEET: FLEET} | ({LABEL_ROBOT: robot} if robot else {})
        return [r for r in self.cloud.resources.values()
                if (kind is None or r.kind == kind) and all(r.labels.get(k) == v for k, v in labels.items())]

    def spec(self, robot: str, index: int):
        return clone_spec(self.provider.inv, robot, index, INFO.bake_base)

    def fail_create_after_instance(self, robot: str) -> None:
        self.cloud.refuse_association.add(robot)  # the public address will not attach

    def owned_ids(self, robot: str | None = None) -> set[str]:
        return {r.id for r in self._owned(robot=robot)}

    def add_foreign(self) -> str:
        labels = owner_labels("other", "clone", "robot1")
        return self.cloud.add("instance", "cri-robot1", labels, state="running", common_ip=None, fs={}, console=[]).id

    def exists(self, resource_id: str) -> bool:
        return resource_id in self.cloud.resources

    def add_leak(self) -> str:
        # A public address left behind (a crash between allocating and associating it).
        return self.cloud.add("address", "cri-ghost-ip", owner_labels(FLEET, "clone", "ghost"), ip="203.0.113.250").id

    def public_ingress(self) -> set[tuple[str, int, str]]:
        """The rules of the fleet's firewall that admit more than the common network."""
        common = str(self.provider.inv.common.cidr)
        return {tuple(rule) for fw in self._owned("firewall") for rule in fw.data["rules"] if rule[2] != common}

    def user_data_sent(self, robot: str) -> bytes:
        return self._owned("instance", robot)[0].data["user_data"]

    def throttle(self, fraction: float) -> None:
        self.cloud.fraction = fraction

    def delay(self, seconds: float) -> None:
        self.cloud.delay = seconds

    def instance_roles(self, robot: str) -> list[str]:
        return [r.labels.get(LABEL_ROLE, "") for r in self._owned("instance", robot)]

    def instances_for(self, robot: str) -> int:
        return len(self._owned("instance", robot))

    def api_calls(self) -> Counter:
        return Counter(self.cloud.calls)


@contextmanager
def make_harness(tmp_path):
    register(INFO)  # the backend's one line
    try:
        fake = cloud.fresh()
        from tests.memory_backend.provider import MemoryProvider

        provider = MemoryProvider(inventory({"kind": "memory"}), tmp_path / "store")
        provider.backoff = FAST
        provider.bootstrap()
        yield MemoryHarness(provider, fake)
    finally:
        unregister(INFO.kind)
