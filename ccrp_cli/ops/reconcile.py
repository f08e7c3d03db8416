"""Desired fleet (inventory + scale) vs what the provider has: plan, then apply in parallel."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import TYPE_CHECKING, Any, cast

from ..models.addressing import allocate, entry_port
from . import gateway, install_space
from .clones import CloneResult, Progress, StateWriter, delete_clone, ensure_clone, push_relay_config
from ..errors import CcrpError, InputError
from ..fleet import Fleet
from ..models.state import RobotRecord
from ..providers.base import CloneState
from .quotas import check_growth
from ..retry import PollTimeout, poll
from ..services.workloads import NO_SOFTWARE, check_secrets, check_snapshot, snapshot_software, stale_snapshot

if TYPE_CHECKING:
    from ..models.state import FleetState
    from ..providers.base import Lifecycle, Provider, Reaches


def plan(fleet: Fleet, provider: Lifecycle) -> list[dict[str, Any]]:
    """Read-only: what `fleet up` would do for every robot."""
    state = fleet.store.load_state()
    # The workspace read, checked (before the provider is asked) and hashed once. A clone `ccrp
    # deploy` brought to the inventory's software runs it, whatever its snapshot holds.
    inventory_software = snapshot_software(fleet.inventory, fleet.path).digest
    actual = provider.query()
    members = [r.name for r in fleet.members(state)]
    rows = []
    index = fleet.pki.load_index() if fleet.pki.exists() else None
    revoked = {name for name in members if index and fleet.pki.revoked_since(name, index)}
    stale = stale_snapshot(fleet, state, inventory_software)
    deployed = install_space.saved(fleet, inventory_software) is not None
    check_secrets(fleet, state, members)
    for name in members:
        rec = actual.get(name)
        if name in revoked:
            action = "leave (robot revoked)"
        elif rec is None:
            action = "create"
        elif rec.state is not CloneState.RUNNING:
            action = f"start ({rec.status})"
        elif state.robots.get(name) and state.robots[name].phase == "ready":
            action = "keep"
        else:
            action = "configure"
        note = _software_note(state, name, stale, inventory_software,
                              deployed and rec.state is not CloneState.RUNNING) if rec is not None else None
        rows.append({"robot": name, "action": action, "provider_id": rec.provider_id if rec else None,
                     "software": note,
                     "endpoint": _endpoint_note(fleet, state, name)})
    for name, rec in actual.items():
        if name not in members:
            rows.append({"robot": name, "action": "delete (not in fleet)", "provider_id": rec.provider_id})
    return rows


def _endpoint_note(fleet: Fleet, state: FleetState, robot: str) -> str | None:
    """Where the robot will dial its clone after `fleet up`, said when it is not where its bundle
    dials now (the fleet's provider.entry changed: the robot needs its new bundle)."""
    rec = state.robots.get(robot)
    have = rec.public_endpoint if rec else None
    if gateway.in_use(fleet):
        port = f"the entry gateway's port {entry_port(fleet.inventory, rec.index)}" if rec else "the entry gateway"
        want = gateway.endpoint(fleet, state, robot) or port
    elif state.gateway is not None and have is not None and have.startswith(f"{state.gateway.public_ip}:"):
        want = "its clone's own address"
    else:
        return have
    return want if have in (None, want) else f"{want} (was {have}: new robot bundle)"


def _software_note(state: FleetState, robot: str, stale: str | None, inventory_software: str | None = None,
                   pending: bool = False) -> str | None:
    """Whether robot's clone runs the inventory's software (docs/workloads.md): None when it does.
    `pending`: the clone is not running and `ccrp deploy` kept the inventory's software, which it
    gets when it starts."""
    rec = state.robots.get(robot)
    if pending and rec is not None and rec.software != inventory_software:
        return f"pending: runs software {rec.software or NO_SOFTWARE}, gets the deployed {inventory_software} when it starts"
    if stale is not None:
        if rec is not None and rec.software is not None and rec.software == inventory_software:
            return None  # deployed (`ccrp deploy`)
        return f"{stale}: ccrp deploy, or build a new snapshot and re-create the clone"
    want = (state.snapshot or {}).get("software", NO_SOFTWARE)
    # A clone from before software digests were recorded (None) ran no software of the user's.
    have = (rec.software or NO_SOFTWARE) if rec is not None else want
    if have != want:
        return f"runs software {have}, the snapshot holds {want}: ccrp deploy, or re-create the clone"
    return None


def _fan_out(fn: Callable[[str], CloneResult], robots: list[str], progress: Progress, provider: Lifecycle,
             stop: threading.Event | None = None, at_most: int | None = None) -> list[CloneResult]:
    """fn(robot) for every robot on a pool bounded by the provider: its max_parallel says how many
    clones it can create at once (CPU-bound local containers vs API-latency-bound clouds), and
    `at_most`, when given, bounds it further (`deploy --max-parallel`).

    Ctrl-C reaches the main thread only, which waits here: then no robot not yet started starts,
    `stop` is set for the running ones (ccrp deploy's put their clones back; others finish what
    they do), each robot left out is named, and the interruption goes on once they are done."""
    stop = stop if stop is not None else threading.Event()

    def run(robot: str) -> CloneResult:
        t0 = time.monotonic()
        if stop.is_set():
            return CloneResult(robot, "not started", "interrupted")
        try:
            return fn(robot)
        except CcrpError as exc:
            progress(f"[{robot}] failed: {exc.one_line()}")
            return CloneResult(robot, "failed", exc.one_line(), time.monotonic() - t0)
        except Exception as exc:  # noqa: BLE001 - one robot's surprise must not stop the others
            progress(f"[{robot}] failed: {type(exc).__name__}: {exc}")
            return CloneResult(robot, "failed", f"{type(exc).__name__}: {exc}", time.monotonic() - t0)

    if not robots:
        return []
    pool = ThreadPoolExecutor(max_workers=min(provider.max_parallel, at_most or len(robots), len(robots)))
    futures = [pool.submit(run, robot) for robot in robots]
    try:
        _wait_all(futures)
    except KeyboardInterrupt:
        stop.set()
        for f in futures:
            f.cancel()
        busy = [r for r, f in zip(robots, futures) if f.running()]
        if busy:
            progress(f"interrupted: waiting for {', '.join(busy)} (no other clone is started)")
        while True:
            try:
                _wait_all([f for f in futures if not f.cancelled()])
                break
            except KeyboardInterrupt:  # again: still the same answer, the clones must not be left half done
                progress(f"still waiting for {', '.join(r for r, f in zip(robots, futures) if f.running())}")
        for robot, f in zip(robots, futures):
            if f.cancelled() or f.result().action == "not started":
                progress(f"[{robot}] not started: interrupted")
        raise
    finally:
        pool.shutdown(wait=False)
    return [f.result() for f in futures]


def _wait_all(futures: list[Future[CloneResult]]) -> None:
    """Until every future is done, waking every 0.5 s: Ctrl-C is then seen at once whichever of the
    process's threads the signal reached (the main thread's handler runs at its next wake)."""
    while not all(f.done() for f in futures):
        wait(futures, timeout=0.5)


def up(fleet: Fleet, provider: Provider, progress: Progress, only: list[str] | None = None,
       quotas_checked: bool = False) -> list[CloneResult]:
    """Create or reuse every member's clone; delete clones of robots no longer in the fleet.
    Refused (QuotaError) before anything is created when the clones it would create need more
    of a cloud quota than is free; `quotas_checked`: the caller did that already."""
    state = fleet.load_allocated()
    writer = StateWriter(fleet, state)
    members = [r.name for r in fleet.members(state)]
    targets = [r for r in members if only is None or r in only]
    deployed = _check_software(fleet, state, provider, targets)  # before any clone changes
    if not quotas_checked:
        check_growth(fleet, provider, targets, progress)
    provider.bootstrap()
    if gateway.in_use(fleet) or state.gateway is not None:  # before the clones: their robots' endpoints are its address
        (gateway.ensure if gateway.in_use(fleet) else gateway.retire)(fleet, provider, state, progress)
        with writer.lock:
            fleet.store.save_state(state)
    # Every missing certificate in one write (ensure_clone then finds them): per robot, this
    # costs the same in a fleet of 10 or of 1,000.
    plan = fleet.plan(state)
    fleet.pki.issue_fleet({r: str(plan[r].common_ip) for r in targets}, fleet.inventory.vpn.cert_days)
    results = _fan_out(lambda r: ensure_clone(fleet, provider, writer, r, progress, deployed), targets, progress,
                       provider)
    if only is None:
        strays = [name for name in provider.query() if name not in members]
        results += retire(fleet, provider, writer, strays, progress, forget=True)
    reshare(fleet, provider, progress, writer.relay_current)
    return results


def _check_software(fleet: Fleet, state: FleetState, provider: Lifecycle, targets: list[str]) -> tuple[str, str] | None:
    """Refuse when a clone would not run the inventory's software: one the snapshot would make while
    it holds other software, or one that runs other software. A clone `ccrp deploy` brought to the
    inventory's software is started or reused as it is: after a deploy, `clone start` and `fleet up`
    were refused for the snapshot's older version (met on a real OpenStack, docs/openstack.md).
    Returns (digest, install space) when a deploy of the inventory's software is kept: the clones
    made or started then get it (ensure_clone)."""
    check_secrets(fleet, state, targets)
    want = snapshot_software(fleet.inventory, fleet.path).digest
    payload = install_space.saved(fleet, want)
    deployed = (want, payload) if payload is not None else None
    if deployed is not None or stale_snapshot(fleet, state, want) is None:
        return deployed
    existing = provider.query()
    if all(r in existing and state.robots.get(r) is not None and state.robots[r].software == want for r in targets):
        return None
    check_snapshot(fleet, state, provider.kind)
    return None


# The agents on a clone that reopen a Zenoh session when their peer list changes, by their reports.
PEER_REPORTS = ("/run/ccrp-relay/status.json", "/run/ccrp-knowledge/status.json")
DRAIN_TIMEOUT = 10.0


def retire(fleet: Fleet, provider: Lifecycle, writer: StateWriter, robots: list[str], progress: Progress,
           forget: bool) -> list[CloneResult]:
    """Delete the robots' clones once their partners have let go of them. A partner's relay and
    knowledge agents open a new Zenoh session when their peer list changes; closing the old one
    takes milliseconds while the leaving clone still answers, but once it is gone Zenoh waits 10 s
    on the dead link and then gave up the close half done: the links to the other partners were
    not dialled again within 20 s (seen in CI). So: the leaving clones drop out of every relay
    config first, the partners are given up to DRAIN_TIMEOUT s to apply that, then they go."""
    if not robots:
        return []
    for robot in robots:
        if robot in writer.state.robots:
            writer.update(robot, phase="deleting")  # out of every relay config (relay_config's `live`)
    drain(provider, reshare(fleet, provider, progress), set(robots), progress)
    return _fan_out(lambda r: delete_clone(fleet, provider, writer, r, forget), robots, progress, provider)


def drain(provider: Reaches, partners: list[str], leaving: set[str], progress: Progress) -> None:
    """Wait until no agent report on `partners` names a `leaving` peer (a report missing, or over
    10 s old, is an agent that is not running: nothing to wait for)."""
    def holding(robot: str) -> bool:
        for path in PEER_REPORTS:
            rc, out = provider.transport.exec(robot, ["cat", path], timeout=10)
            try:
                report = json.loads(out) if rc == 0 else {}
            except ValueError:
                continue
            if time.time() - report.get("time", 0) < 10 and leaving & set(report.get("peers") or {}):
                return True
        return False

    try:
        poll(lambda: (not (left := [r for r in partners if holding(r)]), left), timeout=DRAIN_TIMEOUT, interval=0.5)
    except CcrpError as exc:  # a partner that stopped answering: its links go with it anyway
        progress(f"not waiting for partners to let go: {exc.one_line()}")
    except PollTimeout as exc:
        still = cast("list[str]", exc.last)  # the probe's answer: the partners still linked
        progress(f"{', '.join(still)} still linked to {', '.join(sorted(leaving))} after {exc.seconds:.0f} s; deleting anyway")


def reshare(fleet: Fleet, provider: Lifecycle, progress: Progress, known: dict[str, str] | None = None) -> list[str]:
    """Push the current relay config to every clone that is up (the agents apply it without a
    restart). `known`: robot -> the relay.json this run already found on its clone; those that
    still match are not asked again. Returns the robots whose config changed."""
    state = fleet.store.load_state()
    known = known or {}
    ready = [n for n, rec in state.robots.items() if rec.phase == "ready"]
    if any(n not in known for n in ready):
        # A clone that stopped itself (autostop) is still `ready`: its next start gets the config.
        running = {n for n, rec in provider.query().items() if rec.state is CloneState.RUNNING}
        ready = [n for n in ready if n in known or n in running]

    def one(robot: str) -> CloneResult:
        changed = push_relay_config(fleet, provider, state, robot, known.get(robot))
        return CloneResult(robot, "reconfigured" if changed else "unchanged")

    results = _fan_out(one, ready, progress, provider)
    changed = [r.robot for r in results if r.action == "reconfigured"]
    if changed:
        progress(f"topic sharing reconfigured on {', '.join(changed)}")
    return changed


def check_scale(fleet: Fleet, state: FleetState, size: int) -> tuple[list[str], int]:
    """The fleet's template robots (oldest first) and how many of them `size` wants; InputError
    when the inventory cannot give `size` (callers check first, before they make anything)."""
    inv = fleet.inventory
    named = len(inv.robots)
    if size < named:
        raise InputError(
            f"fleet {fleet.name!r} names {named} robots in its inventory; cannot scale to {size}",
            hint="remove robots from the inventory to go below that",
        )
    template = [n for n, r in sorted(state.robots.items(), key=lambda kv: kv[1].index) if r.origin == "template"]
    want = size - named
    if want > len(template) and inv.template is None:
        raise InputError(f"fleet {fleet.name!r} has no template for new robots", hint="add a `template:` to the inventory")
    if inv.template and want > inv.template.max:
        raise InputError(f"template.max is {inv.template.max}; cannot add {want} template robots")
    return template, want


def scaled(fleet: Fleet, state: FleetState, size: int) -> tuple[list[str], list[str], list[str]]:
    """What scaling to `size` does: the members kept, the new template robots (named with the
    first free numbers), the template robots removed (the newest first)."""
    inv = fleet.inventory
    template, want = check_scale(fleet, state, size)
    removed = template[want:]
    new: list[str] = []
    k = 1
    taken = set(state.robots) | {r.name for r in inv.robots}
    while len(template) + len(new) < want:
        name = f"{inv.template.prefix}{k}"  # type: ignore[union-attr]
        if name not in taken:
            new.append(name)
        k += 1
    return [r.name for r in fleet.members(state) if r.name not in removed], new, removed


def scale(fleet: Fleet, provider: Provider, size: int, progress: Progress) -> list[CloneResult]:
    """Grow or shrink the fleet to `size` clones with template robots; inventory robots stay."""
    state = fleet.store.load_state()
    kept, new, removed = scaled(fleet, state, size)
    _check_software(fleet, state, provider, kept + new)
    if new:
        # Quotas before growth: the new robots (and any member whose clone is missing) are held
        # against the cloud's quotas before they are recorded or anything is created.
        check_growth(fleet, provider, kept + new, progress)
        existing = {n: r.index for n, r in state.robots.items()}
        slots = allocate(fleet.inventory, [*existing, *new], existing)
        for name in new:
            state.robots[name] = RobotRecord(index=slots[name], origin="template")
        fleet.store.save_state(state)
    writer = StateWriter(fleet, state)
    results = retire(fleet, provider, writer, removed, progress, forget=True)
    return results + up(fleet, provider, progress, quotas_checked=bool(new))


def down(fleet: Fleet, provider: Provider, progress: Progress) -> list[str]:
    """Remove everything ccrp created for the fleet, then verify nothing carrying its labels is left."""
    removed = provider.teardown()
    left = provider.leftovers()
    if left:
        raise CcrpError(f"fleet down left {len(left)} resources: {', '.join(left[:5])}", hint="run `ccrp fleet down` again")
    state = fleet.store.load_state()
    for rec in state.robots.values():
        rec.clear_clone()
    state.gateway = None  # its address went with it
    fleet.store.save_state(state)
    progress(f"fleet {fleet.name!r} is down: removed {len(removed)} resources, none left")
    return removed
