"""What ccrp knows exists for a fleet: address allocations, provider ids, lifecycle phase."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict

from .values import EndpointText

SCHEMA_VERSION = 1

# revoked: the robot's certificate was revoked; its clone is left as it is, out of sharing.
Phase = Literal["planned", "creating", "ready", "failed", "deleting", "revoked"]


class RobotRecord(BaseModel):
    model_config = ConfigDict(extra="forbid")

    # Slot in the address plan; kept for the robot's life so addresses never shift.
    index: int
    origin: Literal["inventory", "template"] = "inventory"
    phase: Phase = "planned"
    provider_id: str | None = None
    # Host or IP (and port) the robot dials for its VPN; known once the clone exists. Checked when
    # state.json is read: it is written into the robot's .ovpn, which root runs on the robot.
    public_endpoint: EndpointText | None = None
    addresses: dict[str, str] = {}

    def clear_clone(self) -> None:
        """The clone is gone; the robot keeps its slot (and so its addresses)."""
        self.phase, self.provider_id, self.public_endpoint, self.addresses = "planned", None, None, {}


class FleetState(BaseModel):
    model_config = ConfigDict(extra="forbid")

    schema_version: int = SCHEMA_VERSION
    fleet: str
    robots: dict[str, RobotRecord] = {}
    snapshot: dict[str, str] | None = None
