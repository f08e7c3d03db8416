"""The verbs on one robot's clone, each whole (PKI, fleet lock, snapshot, reconcile, the result):
`ccrp clone create`, `start`, `stop`, `restart` and `delete`, and the dashboard's Start and Restart
buttons. clones.py is the machinery that converges one clone; these are what a user asks of it.
docs/architecture.md "Code map"."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from . import reconcile
from .. import retry
from .clones import CloneResult, StateWriter
from .snapshots import ensure_snapshot
from .vpn import ensure_pki
from ..errors import CcrpError, InputError
from ..providers.base import CloneState, Origin

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Lifecycle, Provider
    from .clones import Progress


def clone_create(fleet: Fleet, provider: Provider, robot: str, say: Progress) -> list[CloneResult]:
    """`ccrp clone create`: create or reuse one robot's clone, as `fleet up` does for every robot."""
    fleet.robot(fleet.store.load_state(), robot)  # an unknown robot is bad input, before any PKI is made
    ensure_pki(fleet, say)
    with fleet.store.lock():
        ensure_snapshot(fleet, provider, say, robots=[robot])
        return reconcile.up(fleet, provider, say, only=[robot])


def clone_delete(fleet: Fleet, provider: Provider, robot: str, say: Progress) -> list[CloneResult]:
    """`ccrp clone delete`: the robot's clone and its secrets volume go (the robot keeps its
    certificates and addresses)."""
    with fleet.store.lock():
        state = fleet.store.load_state()
        existed = robot in provider.query()
        [item] = reconcile.retire(fleet, provider, StateWriter(fleet, state), [robot], say, forget=False)
        if not existed:
            item.action = "absent"
    return [item]


def clone_start(fleet: Fleet, provider: Provider, robot: str, say: Progress) -> list[CloneResult]:
    """`ccrp clone start`: start the robot's stopped clone, push its keys again, wait until it serves."""
    fleet.robot(fleet.store.load_state(), robot)
    # Asked first: `fleet up` would create a clone that does not exist, and `clone start` must not.
    if robot not in provider.query():
        raise InputError(f"robot {robot!r} has no clone to start", hint=f"ccrp clone create --robot {robot}")
    with fleet.store.lock():
        items = reconcile.up(fleet, provider, say, only=[robot])
    if items[0].origin is Origin.RESUMED:  # the provider started it (it was running: `reused`)
        items[0].action = "started"
    return items


def clone_stop(fleet: Fleet, provider: Lifecycle, robot: str, say: Progress, timeout: float = 300) -> list[CloneResult]:
    """`ccrp clone stop`: the provider stops the robot's clone (its disk, addresses and keys stay)
    and ccrp waits until it says stopped. `clone start`, or the next `fleet up`, starts it again."""
    fleet.robot(fleet.store.load_state(), robot)
    t0 = time.monotonic()
    with fleet.store.lock():
        rec = provider.query().get(robot)
        if rec is None:
            raise InputError(f"robot {robot!r} has no clone to stop", hint=f"ccrp clone create --robot {robot}")
        if rec.state is CloneState.STOPPED:
            return [CloneResult(robot, "stopped", "stopped already")]
        say(f"{robot}: stopping its clone ({rec.status})")
        provider.stop_instance(robot)

        def stopped() -> tuple[bool, str]:
            now = provider.query().get(robot)
            return now is not None and now.state is CloneState.STOPPED, now.status if now else "gone"
        try:
            retry.poll(stopped, timeout=timeout, interval=2, every=30,
                       progress=lambda s: say(f"{robot}: still stopping after {s:.0f} s"))
        except retry.PollTimeout as exc:
            raise CcrpError(f"the clone of {robot} did not stop within {exc.seconds:.0f} s (it is {exc.last})",
                            hint=f"ccrp clone stop --robot {robot} again, or look at it in the cloud's console") from None
    return [CloneResult(robot, "stopped", "", time.monotonic() - t0)]


def clone_restart(fleet: Fleet, provider: Provider, robot: str, say: Progress) -> list[CloneResult]:
    """`ccrp clone restart`: stop the clone, then `clone start`. The provider stops it, so a clone
    that no longer answers (a hung master, a full disk, lost keys) restarts too."""
    stopped = clone_stop(fleet, provider, robot, say)
    items = clone_start(fleet, provider, robot, say)
    if items[0].action in ("started", "reused"):
        items[0].action = "restarted"
    items[0].seconds += stopped[0].seconds
    return items
