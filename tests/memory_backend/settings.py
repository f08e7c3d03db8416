"""`provider:` of an inventory for the memory backend (tests only)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from ccrp_cli.models.strict import ProviderSettings


class MemorySettings(ProviderSettings):
    kind: Literal["memory"]
    # The memory cloud's quota on instances (any fleet's): what `fleet plan` and the quota check read.
    max_instances: Annotated[int, Field(strict=True, ge=0)] = 50
