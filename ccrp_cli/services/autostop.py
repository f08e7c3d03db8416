"""Autostop (docs/architecture.md, "A clone stops itself"): agent/autostop.py as ccrp-autostop.service,
in every clone's user-data; its setting is a pushed file, re-read at every check, so a change needs
`fleet up`, not a new clone."""

from __future__ import annotations

import json

from ..fleet import Fleet
from ..models.layout import CCRP_ETC
from ..models.inventory import Robot
from ..models.state import FleetState
from ..render.files import BundleFile
from .base import Boot, CloneService, ServiceContext


def autostop_file(fleet: Fleet, robot: Robot) -> BundleFile:
    """The clone's autostop setting (agent/autostop.py reads it at every check)."""
    text = json.dumps({"robot": robot.name, "idle": fleet.inventory.idle_of(robot)}) + "\n"
    return BundleFile("autostop.json", text, 0o644, f"{CCRP_ETC}/autostop.json")


class Autostop(CloneService):
    name = "autostop"
    # Before the keys: the agent counts idle time from when OpenVPN serves (see ensure_clone).
    settings = True
    # 0755 as the user-data always wrote it (its unit runs it with python3 either way).
    boot = Boot(units=("ccrp-autostop.service",), agents=("autostop",), agent_mode="0755")

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        return [autostop_file(ctx.fleet, ctx.robot)]

    def status(self, fleet: Fleet, state: FleetState, robot: Robot, health: dict | None) -> dict:
        return {"autostop_idle_s": fleet.inventory.idle_of(robot) or None}
