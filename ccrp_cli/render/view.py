"""What every renderer needs to know about one clone and its robot."""

from __future__ import annotations

from dataclasses import dataclass

from ..models.addressing import CloneAddresses
from ..models.layout import POWER_PORT, SECRETS_DIR, VPN_DIR
from ..models.inventory import Inventory, Robot


@dataclass(frozen=True)
class CloneView:
    inv: Inventory
    robot: Robot
    addr: CloneAddresses
    # The other clones of the fleet (for /etc/hosts and topic sharing).
    peers: tuple[CloneAddresses, ...] = ()

    @property
    def fleet(self) -> str:
        return self.inv.fleet

    @property
    def name(self) -> str:
        return self.robot.name

    @property
    def operator_cidr(self) -> str | None:
        cidr = self.inv.provider.operator_network()
        return str(cidr) if cidr else None

    @property
    def knowledge_port(self) -> int | None:
        """The knowledge agents' port, when this clone shares a dataset (its firewall opens it to the
        common network)."""
        k = self.inv.services.knowledge
        return k.port if k is not None and self.inv.may_share_knowledge(self.name) else None

    def ctx(self, **extra: object) -> dict[str, object]:
        """Template context shared by all templates."""
        return {
            "fleet": self.fleet,
            "robot": self.name,
            "a": self.addr,
            "vpn": self.inv.vpn,
            "ros": self.inv.ros,
            "sharing": self.inv.sharing,
            "common_cidr": self.inv.common.cidr,
            "operator_cidr": self.operator_cidr,
            "vpn_dir": VPN_DIR,
            "secrets_dir": SECRETS_DIR,
            "knowledge_port": self.knowledge_port,
            "power_port": POWER_PORT,
            **extra,
        }
