"""What ccrp knows exists for a fleet: address allocations, provider ids, lifecycle phase."""

from __future__ import annotations

import ipaddress
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from .values import EndpointText

SCHEMA_VERSION = 1

# revoked: the robot's certificate was revoked; its clone is left as it is, out of sharing.
Phase = Literal["planned", "creating", "ready", "failed", "deleting", "revoked"]


class RobotRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    # Slot in the address plan; kept for the robot's life so addresses never shift. Both are
    # fixed once recorded (Fleet keeps its address plan while the records stay the same).
    index: int = Field(frozen=True)
    origin: Literal["inventory", "template"] = Field("inventory", frozen=True)
    phase: Phase = "planned"
    provider_id: str | None = None
    # Host or IP (and port) the robot dials for its VPN; known once the clone exists. Checked when
    # state.json is read: it is written into the robot's .ovpn, which root runs on the robot.
    public_endpoint: EndpointText | None = None
    addresses: dict[str, str] = {}
    # The snapshot its clone was created from (kept by snapshot retention while the clone lives).
    image: str | None = None
    # The digest of the user's software that snapshot held (docs/workloads.md).
    software: str | None = None
    # The apt/pip packages that snapshot held (workloads.packages_record): `ccrp deploy` changes
    # the workspace only, so it refuses an inventory whose packages differ.
    packages: str | None = None

    def clear_clone(self) -> None:
        """The clone is gone; the robot keeps its slot (and so its addresses)."""
        self.phase, self.provider_id, self.public_endpoint, self.addresses, self.image = "planned", None, None, {}, None
        self.software = self.packages = None


class GatewayRecord(BaseModel):
    """The fleet's entry gateway (provider.entry: gateway), once `fleet up` has made it: its address
    is in every robot's bundle, with the robot's own port (models/addressing.py entry_port)."""

    model_config = ConfigDict(extra="forbid")

    provider_id: str
    public_ip: ipaddress.IPv4Address
    # The snapshot it was made from (snapshot retention keeps it); None when a gateway made by an
    # earlier ccrp was found, which keeps every snapshot until it is made again.
    image: str | None = None


class FleetState(BaseModel):
    model_config = ConfigDict(extra="forbid")

    schema_version: int = SCHEMA_VERSION
    fleet: str
    robots: dict[str, RobotRecord] = {}
    snapshot: dict[str, str] | None = None
    gateway: GatewayRecord | None = None
    # The software digest `ccrp deploy` last pushed: its install space is kept in the state
    # directory (ops/install_space.py), and a clone started or made later gets it.
    deployed: str | None = None
