"""What every harness builds the same way: fleet "ct" with five robots, and CloneSpecs with the
real rendered user-data of each clone (as clones.ensure_clone does)."""

from __future__ import annotations

from ccrp_cli.loader import inventory_model
from ccrp_cli.models.addressing import addresses
from ccrp_cli.models.inventory import Inventory
from ccrp_cli.providers.base import CloneSpec
from ccrp_cli.retry import Backoff

from .harness import FLEET

ROBOTS = [f"robot{i}" for i in range(1, 6)]
OPERATOR_CIDR = "198.51.100.0/24"
# Storms fail a random third of calls: 20 attempts make a spurious give-up ((1/3)**20 per call)
# negligible, while delays stay tiny so the suite is fast.
FAST = Backoff(attempts=20, base=0.001, cap=0.01)


def inventory(provider: dict, **extra) -> Inventory:
    return inventory_model().model_validate({
        "fleet": FLEET,
        "provider": provider,
        "robots": [{"name": r, "exports": [f"/{r}/odom"]} for r in ROBOTS],
        **extra,
    })


def clone_spec(inv: Inventory, robot: str, index: int, image: str) -> CloneSpec:
    from ccrp_cli.render import cloudinit
    from ccrp_cli.services.registry import boots
    from ccrp_cli.render.view import CloneView

    addr = addresses(inv, robot, index)
    peers = tuple(addresses(inv, r, i) for i, r in enumerate(ROBOTS, 1) if r != robot)
    view = CloneView(inv, inv.robot(robot), addr, peers)
    return CloneSpec(
        robot=robot, hostname=addr.clone_host, image=image, user_data=cloudinit.user_data(view, boots()),
        instance_id=f"{inv.fleet}-{robot}-{index}", common_ip=str(addr.common_ip), vpn_subnet=str(addr.vpn_subnet),
    )


def gateway_spec(inv: Inventory, base: CloneSpec) -> CloneSpec:
    """The entry gateway's spec as ops/gateway.py gives it (robot GATEWAY, role "gateway", the common
    network's fixed gateway address, no VPN subnet), on a clone's image and user-data."""
    from ccrp_cli.models.addressing import gateway_ip
    from ccrp_cli.providers.base import GATEWAY, GATEWAY_ROLE

    return base.model_copy(update={
        "robot": GATEWAY, "role": GATEWAY_ROLE, "hostname": f"ccrp-{inv.fleet}-gateway",
        "instance_id": f"{inv.fleet}-gateway", "common_ip": str(gateway_ip(inv)), "vpn_subnet": None})


class Knobs:
    """The Harness knobs of fakes that count calls in `calls` and read `_fraction`, `_delay` and
    `_fail_robots` themselves (the AWS and Docker harnesses)."""

    def throttle(self, fraction: float) -> None:
        self._fraction = fraction

    def delay(self, seconds: float) -> None:
        self._delay = seconds

    def fail_create_after_instance(self, robot: str) -> None:
        self._fail_robots.add(robot)

    def api_calls(self):
        from collections import Counter

        return Counter(self.calls)
