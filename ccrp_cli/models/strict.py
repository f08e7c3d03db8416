"""The base of every model read from a user's file: unknown keys are errors, not ignored."""

from __future__ import annotations

import ipaddress
from typing import TYPE_CHECKING

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ProviderSettings(Strict):
    """The base of a backend's `provider:` section (providers/<kind>/settings.py)."""

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
