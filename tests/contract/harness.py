"""What the provider contract suite needs from each backend's fake (or real) cloud.

One module per provider, `tests/contract/harness_<kind>.py`, defines
`make_harness(tmp_path) -> contextlib.AbstractContextManager[Harness]`. The context builds a
provider for fleet "ct" from an inventory on top of the fake (moto, openstacksdk fixtures +
requests-mock, autospecced GCP clients, real Docker, the memory backend's cloud) and, on exit, removes
everything it started.
The suite (test_contract.py) only drives the provider through the Provider protocol
(providers/base.py) and inspects the fake through this one.
"""

from __future__ import annotations

from collections import Counter
from typing import Protocol

from ccrp_cli.providers.base import CloneSpec, Provider

FLEET = "ct"


class Harness(Protocol):
    kind: str
    provider: Provider

    def spec(self, robot: str, index: int) -> CloneSpec:
        """A CloneSpec for robot with a valid image/snapshot in the fake and rendered user-data."""

    def fail_create_after_instance(self, robot: str) -> None:
        """Make the next run_instance(robot) fail AFTER the cloud has created the instance (e.g. the
        public IP / floating IP / tagging step fails), so the provider must roll back its partials."""

    def owned_ids(self, robot: str | None = None) -> set[str]:
        """Ids of every resource in the fake that carries fleet "ct"'s labels (for robot, if given),
        read from the fake directly, not through the provider."""

    def add_foreign(self) -> str:
        """Create an instance NOT owned by the fleet (no labels, or another fleet's) named like a
        clone; the provider must never touch it. Returns its id."""

    def exists(self, resource_id: str) -> bool:
        """Whether the fake still holds this resource."""

    def add_leak(self) -> str:
        """Create a resource carrying fleet "ct"'s labels behind the provider's back (a leak that
        state does not know). Returns its id."""

    def public_ingress(self) -> set[tuple[str, int, str]]:
        """(protocol, port, source CIDR) of every ingress rule reachable from outside the common
        network on the fleet's security group(s)/firewall rules."""

    def user_data_sent(self, robot: str) -> bytes:
        """The user-data exactly as the fake received it for robot's instance (decoded from base64,
        still gzipped if the provider gzipped it)."""

    def throttle(self, fraction: float) -> None:
        """From now on, fail this fraction of API calls with HTTP 429/503 (or the SDK's throttling
        error) BEFORE they reach the fake."""

    def delay(self, seconds: float) -> None:
        """From now on, every API call takes this much longer (benchmarks: 200 ms per call)."""

    def kill(self, provider_id: str) -> None:
        """Delete the instance in the fake as an operator or a failure does, around ccrp (what it
        holds apart from the instance stays). Backends with Ability.ENTRY_GATEWAY."""

    def new_provider(self, inv, workdir):
        """A provider of another inventory (the harness's, changed) on the same fake. Backends with
        Ability.ENTRY_GATEWAY."""

    def instance_roles(self, robot: str) -> list[str]:
        """The ccrp-role label of each instance the fake holds for robot, read from the fake."""

    def instances_for(self, robot: str) -> int:
        """How many instances the fake holds for robot (idempotency: must stay 1)."""

    def api_calls(self) -> Counter:
        """Calls that reached the fake (or were throttled), by operation name."""
