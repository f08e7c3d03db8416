"""A fleet as commands see it: inventory + on-disk store + the address plan."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from .addressing import CloneAddresses, addresses, allocate, capacity
from .errors import InputError, shown
from .loader import load_inventory
from .models.inventory import Inventory, Robot
from .models.state import FleetState, RobotRecord
from .pki.store import PkiStore
from .store import FleetStore


@dataclass
class Fleet:
    inventory: Inventory
    store: FleetStore

    @classmethod
    def open(cls, inventory_path: str | Path) -> "Fleet":
        inv = load_inventory(inventory_path)
        if len(inv.robots) > capacity(inv):
            raise InputError(
                f"{inventory_path}: {len(inv.robots)} robots but the address pools have room for {capacity(inv)}",
                hint="widen vpn.pool or common.cidr",
            )
        return cls(inv, FleetStore(inv.fleet))

    @property
    def name(self) -> str:
        return self.inventory.fleet

    @cached_property
    def pki(self) -> PkiStore:
        return PkiStore(self.store.pki_dir, self.name)

    def members(self, state: FleetState) -> list[Robot]:
        """Robots in the fleet: those named in the inventory, then template robots in state."""
        robots = list(self.inventory.robots)
        tpl = self.inventory.template
        for name, rec in sorted(state.robots.items(), key=lambda kv: kv[1].index):
            if rec.origin == "template" and tpl is not None:
                robots.append(Robot(name=name, type=tpl.type, exports=tpl.exports, imports=tpl.imports))
        return robots

    def robot(self, state: FleetState, name: str) -> Robot:
        members = self.members(state)
        for robot in members:
            if robot.name == name:
                return robot
        known = ", ".join(r.name for r in members[:10]) + (", ..." if len(members) > 10 else "") or "none"
        raise InputError(f"robot {shown(name)} is not in fleet {self.name!r} (robots: {known})")

    def allocate(self, state: FleetState) -> bool:
        """Give every member an address slot in `state`; True when state changed."""
        names = [r.name for r in self.members(state)]
        existing = {n: rec.index for n, rec in state.robots.items()}
        slots = allocate(self.inventory, names, existing)
        changed = False
        for name, slot in slots.items():
            if name not in state.robots:
                state.robots[name] = RobotRecord(index=slot)
                changed = True
        return changed

    def plan(self, state: FleetState) -> dict[str, CloneAddresses]:
        """Addresses of every member; members without a slot get a provisional one (not saved)."""
        names = [r.name for r in self.members(state)]
        slots = allocate(self.inventory, names, {n: rec.index for n, rec in state.robots.items()})
        return {name: addresses(self.inventory, name, slot) for name, slot in slots.items()}

    def load_allocated(self) -> FleetState:
        """State with a slot for every member, saved. Caller holds the lock."""
        state = self.store.load_state()
        if self.allocate(state):
            self.store.save_state(state)
        return state


def clone_view(fleet: Fleet, state: FleetState, name: str):
    """The render view of robot `name`'s clone (imported lazily: renderers pull in Jinja2)."""
    from .render.view import CloneView

    robot = fleet.robot(state, name)
    plan = fleet.plan(state)
    peers = tuple(a for n, a in plan.items() if n != name)
    return CloneView(fleet.inventory, robot, plan[name], peers)
