"""The base of every model read from a user's file: unknown keys are errors, not ignored."""

from __future__ import annotations

import ipaddress

from pydantic import BaseModel, ConfigDict


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ProviderSettings(Strict):
    """The base of a backend's `provider:` section (providers/<kind>/settings.py)."""

    def networks(self) -> dict[str, ipaddress.IPv4Network]:
        """Networks the backend makes from these settings, by their inventory key: the inventory
        refuses one that overlaps the VPN pool or the common network (clouds make theirs from
        `common.cidr`: none of their own)."""
        return {}

    def place(self) -> str:
        """Where the fleet's clones are, in the backend's words (a region, a cloud), for `ccrp
        doctor`; "" where the settings name none."""
        return ""
