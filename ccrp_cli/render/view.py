"""What every renderer needs to know about one clone and its robot."""

from __future__ import annotations

from dataclasses import dataclass

from ..addressing import CloneAddresses
from ..models.inventory import Inventory, Robot

# Paths on the clone.
VPN_DIR = "/etc/openvpn/server/ccrp"
# What ccrp pushes after boot (keys, certificates, CRL, password hash), never on the clone's root
# disk, so no snapshot of any kind can capture it: a tmpfs on clouds (mounted at every boot by
# the user-data's bootcmd), the clone's own volume on Docker (which `docker commit` leaves out).
SECRETS_DIR = f"{VPN_DIR}/keys"
# OpenVPN's management socket, in a root-only runtime directory made by ccrp-openvpn.service (the
# unit sets it, and agent/health.py has its own copy of the path: it runs on the clone, stdlib only).
MGMT_SOCKET = "/run/ccrp-openvpn/mgmt.sock"
CCRP_ETC = "/etc/ccrp"
# What the clone's autostop agent leaves when it powers the clone off: this file on the clone's
# disk (read from a stopped Docker clone) and the same line on the console (kept by the clouds).
# agent/autostop.py has its own copy of both.
AUTOSTOP_NOTE = "/var/lib/ccrp/autostop.note"
AUTOSTOP_MARK = "ccrp-autostop: "
CCRP_LIB = "/usr/local/lib/ccrp"
# The topic relay runs as its own user: it reads only relay.key and ca.crt in SECRETS_DIR.
RELAY_USER = "ccrp-relay"
# The API manager (docs/services.md) runs as its own user: it reads only its backend's key in
# SECRETS_DIR (google-vision), and its config and status file.
API_USER = "ccrp-api"
# The operator's login on a cloud clone (sudo, the fleet's operator key), created by the clone's
# user-data on every cloud: the base images' own users differ (admin on AWS, debian on OpenStack,
# none on GCP). Docker clones have no login user.
LOGIN_USER = "ccrp"
# The knowledge agent (docs/services.md) runs as its own user: it reads the relay's TLS files (as a
# supplementary member of RELAY_USER's group) and writes only its datasets and runtime directory.
KNOWLEDGE_USER = "ccrp-knowledge"
# The power agent (agent/power.py) runs as its own user, listening on the clone's VPN address at
# POWER_PORT for the robot's power device, the one peer the firewall lets reach it.
POWER_USER = "ccrp-power"
POWER_PORT = 11400


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
        cidr = getattr(self.inv.provider, "operator_cidr", None)
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
