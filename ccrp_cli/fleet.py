"""A fleet as commands see it: inventory + on-disk store + the address plan."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import MappingProxyType
from typing import Any, Callable, Mapping

from .models.addressing import CloneAddresses, addresses, allocate, capacity
from .errors import CcrpError, InputError, shown
from .loader import load_inventory
from .models.inventory import Inventory, Robot
from .models.state import FleetState, RobotRecord
from .pki.store import PkiStore
from .store import FleetStore


@dataclass
class Fleet:
    inventory: Inventory
    store: FleetStore
    # Where the inventory was read from: its `software.workspace` is relative to it.
    path: Path | None = None
    # What members/plan derived from the state's slots, with the slots they came from: a command
    # asks for the view of each clone, and each view needs the whole plan.
    _derived: dict[str, tuple[tuple, Any]] = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def open(cls, inventory_path: str | Path) -> "Fleet":
        inv = load_inventory(inventory_path)
        if len(inv.robots) > capacity(inv):
            raise InputError(
                f"{inventory_path}: {len(inv.robots)} robots but the address pools have room for {capacity(inv)}",
                hint="widen vpn.pool or common.cidr",
            )
        return cls(inv, FleetStore(inv.fleet), Path(inventory_path).resolve())

    @property
    def name(self) -> str:
        return self.inventory.fleet

    @cached_property
    def pki(self) -> PkiStore:
        return PkiStore(self.store.pki_dir, self.name)

    def _derive(self, what: str, state: FleetState, compute: Callable[[], Any]) -> Any:
        """compute(), kept while state holds the same robot records (the inventory is fixed for a
        Fleet, and a record's slot and origin never change). The records compare by identity
        first, so checking costs little next to what it saves. Fan-out threads may compute the
        same thing twice; either result is right."""
        slots = tuple(state.robots.items())
        kept = self._derived.get(what)
        if kept is None or kept[0] != slots:
            kept = (slots, compute())
            self._derived[what] = kept
        return kept[1]

    def members(self, state: FleetState) -> list[Robot]:
        """Robots in the fleet: those named in the inventory, then template robots in state."""
        def compute() -> tuple[Robot, ...]:
            robots = list(self.inventory.robots)
            tpl = self.inventory.template
            for name, rec in sorted(state.robots.items(), key=lambda kv: kv[1].index):
                if rec.origin == "template" and tpl is not None:
                    robots.append(Robot(name=name, type=tpl.type, exports=tpl.exports, imports=tpl.imports,
                                        autostop=tpl.autostop, software=tpl.software))
            return tuple(robots)

        return list(self._derive("members", state, compute))

    def _by_name(self, state: FleetState) -> dict[str, Robot]:
        return self._derive("by_name", state, lambda: {r.name: r for r in self.members(state)})

    def robot(self, state: FleetState, name: str) -> Robot:
        by_name = self._by_name(state)
        if name in by_name:
            return by_name[name]
        members = self.members(state)
        known = ", ".join(r.name for r in members[:10]) + (", ..." if len(members) > 10 else "") or "none"
        raise InputError(f"robot {shown(name)} is not in fleet {self.name!r} (robots: {known})")

    def allocate(self, state: FleetState) -> bool:
        """Give every member an address slot in `state`; True when state changed."""
        if self._by_name(state).keys() <= state.robots.keys():
            return False
        names = [r.name for r in self.members(state)]
        existing = {n: rec.index for n, rec in state.robots.items()}
        slots = allocate(self.inventory, names, existing)
        changed = False
        for name, slot in slots.items():
            if name not in state.robots:
                state.robots[name] = RobotRecord(index=slot)
                changed = True
        return changed

    def plan(self, state: FleetState) -> Mapping[str, CloneAddresses]:
        """Addresses of every member; members without a slot get a provisional one (not saved)."""
        def compute() -> Mapping[str, CloneAddresses]:
            names = [r.name for r in self.members(state)]
            slots = allocate(self.inventory, names, {n: rec.index for n, rec in state.robots.items()})
            return MappingProxyType({name: addresses(self.inventory, name, slot) for name, slot in slots.items()})

        return self._derive("plan", state, compute)

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


def snapshot_image(state: FleetState) -> str:
    if not state.snapshot or not state.snapshot.get("image"):
        raise CcrpError("the fleet has no snapshot to create clones from", hint="run `ccrp snapshot build -i INVENTORY`")
    return state.snapshot["image"]
