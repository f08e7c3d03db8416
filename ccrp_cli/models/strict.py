"""The base of every model read from a user's file: unknown keys are errors, not ignored."""

from __future__ import annotations

import ipaddress
from typing import TYPE_CHECKING, ClassVar, Literal

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ProviderSettings(Strict):
    """The base of a backend's `provider:` section (providers/<kind>/settings.py). The inventory
    holds one of these; the loader validates the section with the settings classes the registry
    holds (loader.inventory_model), so models/ never imports providers/."""

    # What the inventory asks of the backend, set on its settings class by the registry from its
    # ProviderInfo (providers/registry.py declare): the recipe's platform its clones run, and
    # whether it bakes images (Ability.BAKE).
    platform: ClassVar[str] = ""
    bakes: ClassVar[bool] = False
    # Whether it can give a fleet one entry gateway (Ability.ENTRY_GATEWAY), set by the registry too.
    gateways: ClassVar[bool] = False

    # How robots reach their clones (docs/architecture.md "Entry gateway"): each clone at a public
    # address of its own, or every robot at its own port of the fleet's one gateway.
    entry: Literal["per-clone", "gateway"] = "per-clone"

    if TYPE_CHECKING:  # each backend's settings declare it as their Literal (the union's discriminator)
        kind: str

    def networks(self) -> dict[str, ipaddress.IPv4Network]:
        """Networks the backend makes from these settings, by their inventory key: the inventory
        refuses one that overlaps the VPN pool or the common network (clouds make theirs from
        `common.cidr`: none of their own)."""
        return {}

    def place(self) -> str:
        """Where the fleet's clones are, in the backend's words (a region, a cloud), for `ccrp
        doctor`; "" where the settings name none."""
        return ""

    def operator_network(self) -> ipaddress.IPv4Network | None:
        """Where the operator reaches the clones from (ccrp's SSH), which their firewall admits;
        None where ccrp reaches clones without the network (Docker's exec)."""
        return None

    def bake_image(self) -> str | None:
        """The image `snapshot bake` starts from when the settings name one (the user's own, with
        ROS installed); None: the backend's stock Debian 12 (ProviderInfo.bake_base)."""
        return None
