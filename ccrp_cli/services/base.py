"""What a clone service is (docs/architecture.md, "Clone services"): the relay, autostop, robot power,
the API manager, knowledge sync, the robot's nodes, the camera view. Each says what it adds to the
user-data, what `fleet up` pushes to a clone for it after boot and how it applies it; the clone
pipeline (clones.py ensure_clone) runs them in the registry's order (registry.py). A service
imports neither the pipeline nor the registry (the `services` import contract), so adding one
touches its own module and one registry line."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Protocol

from ..render.boot import Boot  # what a service adds to user-data: render/ writes it, so it is render's

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..models.inventory import Robot
    from ..models.state import FleetState
    from ..providers.base import Reaches
    from ..render.files import BundleFile


@dataclass(frozen=True)
class ServiceContext:
    """What a service's files are made from, for one clone."""

    fleet: Fleet
    state: FleetState
    robot: Robot
    # The clones taken as up (StateWriter.live()); None: those the state calls ready.
    live: set[str] | None = None
    # The software digest the clone runs (its snapshot's, or what `ccrp deploy` left on a kept clone).
    software: str | None = None


class CloneService(Protocol):
    """One clone service. A service subclasses this and keeps the defaults of what it lacks."""

    name: ClassVar[str]
    # Its files are settings its agent re-reads, pushed before the keys (see ensure_clone); the
    # others are applied once the clone serves.
    settings: ClassVar[bool] = False
    # Its files name the clone's partners: reshare (reconcile.py) pushes them again when the
    # fleet's membership changes, and ensure_clone tells it what this run left on the clone.
    reshared: ClassVar[bool] = False
    # What it adds to every clone's user-data (render/boot.py), which render/cloudinit.py writes.
    boot: ClassVar[Boot] = Boot()

    def check(self, fleet: Fleet, robot: Robot) -> None:
        """Refuse, before the clone is made, what the operator's inputs make impossible."""
        return None  # a service with nothing to refuse (a body: mypy takes an empty one as abstract)

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        """What `fleet up` pushes for it to ctx.robot's clone; [] when that clone runs none."""
        return []

    def absent(self) -> list[BundleFile]:
        """Probed when files() is []: the file (content unused) whose presence says the clone ran
        the service before and apply() must turn it off."""
        return []

    def apply(self, clone: Reaches, robot: str, files: list[BundleFile], have: dict[str, str],
              pushed_keys: bool) -> list[str]:
        """Bring the clone in line with `files`, given the digests it holds (`have`, probed before
        anything was pushed) and whether its keys were just pushed (OpenVPN and the relay
        restarted). Runs once the clone serves. Returns what it started or restarted, for the
        progress line."""
        return []

    def verify(self, clone: Reaches, robot: str, files: list[BundleFile], started: list[str],
               booted: bool) -> str | None:
        """Whether what apply() `started`, and on a clone that has just `booted` what started with
        it, stays up: None, or why not in one line (the clone is kept and recorded; the command
        fails for its robot)."""
        return None

    def status(self, fleet: Fleet, state: FleetState, robot: Robot, health: dict | None) -> dict:
        """Its fields of robot's `ccrp status` row (models/status.py StatusRow), from the clone's
        health report (None: the clone was not asked)."""
        return {}
