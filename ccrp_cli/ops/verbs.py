"""Operations a user starts from the CLI or from the dashboard, each whole (PKI, fleet lock,
snapshot, reconcile, the result): one body each, so `ccrp clone start` and the dashboard's Start
button do exactly the same thing. docs/architecture.md "Code map" lists every verb's function.

`say` receives progress lines (the CLI prints them on stderr, the dashboard pushes them to the
page). Each returns what the CLI renders: per-robot results or certificate records.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

if TYPE_CHECKING:
    from ..providers.base import HostImages, Lifecycle, Provider

Say = Callable[[str], None]


def fleet_up(fleet, provider: Provider, say: Say) -> list:
    """`ccrp fleet up`: create or reuse every robot's clone (the PKI and the snapshot first if the fleet has none)."""
    from . import reconcile

    ensure_pki(fleet, say)
    with fleet.store.lock():
        ensure_snapshot(fleet, provider, say)
        return reconcile.up(fleet, provider, say)


def fleet_down(fleet, provider: Provider, say: Say) -> list[str]:
    """`ccrp fleet down`: remove what ccrp created for the fleet (PKI and state stay)."""
    from . import reconcile

    with fleet.store.lock():
        return reconcile.down(fleet, provider, say)


def clone_create(fleet, provider: Provider, robot: str, say: Say) -> list:
    """`ccrp clone create`: create or reuse one robot's clone, as `fleet up` does for every robot."""
    from . import reconcile

    fleet.robot(fleet.store.load_state(), robot)  # an unknown robot is bad input, before any PKI is made
    ensure_pki(fleet, say)
    with fleet.store.lock():
        ensure_snapshot(fleet, provider, say, robots=[robot])
        return reconcile.up(fleet, provider, say, only=[robot])


def clone_delete(fleet, provider: Provider, robot: str, say: Say) -> list:
    """`ccrp clone delete`: the robot's clone and its secrets volume go (the robot keeps its
    certificates and addresses)."""
    from .clones import StateWriter
    from .reconcile import retire

    with fleet.store.lock():
        state = fleet.store.load_state()
        existed = robot in provider.query()
        [item] = retire(fleet, provider, StateWriter(fleet, state), [robot], say, forget=False)
        if not existed:
            item.action = "absent"
    return [item]


def clone_start(fleet, provider: Provider, robot: str, say: Say) -> list:
    """`ccrp clone start`: start the robot's stopped clone, push its keys again, wait until it serves."""
    from . import reconcile
    from ..errors import InputError
    from ..providers.base import Origin

    fleet.robot(fleet.store.load_state(), robot)
    # Asked first: `fleet up` would create a clone that does not exist, and `clone start` must not.
    if robot not in provider.query():
        raise InputError(f"robot {robot!r} has no clone to start", hint=f"ccrp clone create --robot {robot}")
    with fleet.store.lock():
        items = reconcile.up(fleet, provider, say, only=[robot])
    if items[0].origin is Origin.RESUMED:  # the provider started it (it was running: `reused`)
        items[0].action = "started"
    return items


def clone_stop(fleet, provider: Lifecycle, robot: str, say: Say, timeout: float = 300) -> list:
    """`ccrp clone stop`: the provider stops the robot's clone (its disk, addresses and keys stay)
    and ccrp waits until it says stopped. `clone start`, or the next `fleet up`, starts it again."""
    import time

    from .. import retry
    from .clones import CloneResult
    from ..errors import CcrpError, InputError
    from ..providers.base import CloneState

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

        def stopped():
            now = provider.query().get(robot)
            return now is not None and now.state is CloneState.STOPPED, now.status if now else "gone"
        try:
            retry.poll(stopped, timeout=timeout, interval=2, every=30,
                       progress=lambda s: say(f"{robot}: still stopping after {s:.0f} s"))
        except retry.PollTimeout as exc:
            raise CcrpError(f"the clone of {robot} did not stop within {exc.seconds:.0f} s (it is {exc.last})",
                            hint=f"ccrp clone stop --robot {robot} again, or look at it in the cloud's console") from None
    return [CloneResult(robot, "stopped", "", time.monotonic() - t0)]


def clone_restart(fleet, provider: Provider, robot: str, say: Say) -> list:
    """`ccrp clone restart`: stop the clone, then `clone start`. The provider stops it, so a clone
    that no longer answers (a hung master, a full disk, lost keys) restarts too."""
    stopped = clone_stop(fleet, provider, robot, say)
    items = clone_start(fleet, provider, robot, say)
    if items[0].action in ("started", "reused"):
        items[0].action = "restarted"
    items[0].seconds += stopped[0].seconds
    return items


def fleet_scale(fleet, provider: Provider, size: int, say: Say) -> list:
    """`ccrp fleet scale SIZE`: grow or shrink the fleet with template robots."""
    from . import reconcile

    kept, new, _removed = reconcile.scaled(fleet, fleet.store.load_state(), size)  # bad input makes no PKI, no snapshot
    ensure_pki(fleet, say)
    with fleet.store.lock():
        ensure_snapshot(fleet, provider, say, robots=kept + new)
        return reconcile.scale(fleet, provider, size, say)


def vpn_issue(fleet, robot: str, renew: bool, say: Say) -> list[dict[str, Any]]:
    """`ccrp vpn issue-cert`: the robot's client and its clone's server certificates (the PKI
    first if the fleet has none); with `renew`, a running clone takes the new set at once."""
    from . import vpn
    from ..providers import get_provider

    fleet.robot(fleet.store.load_state(), robot)
    ensure_pki(fleet, say)
    return vpn.issue(fleet, robot, renew, get_provider(fleet.inventory) if renew else None, say)


def vpn_revoke(fleet, provider: Provider, robot: str, say: Say, cert: str = "client") -> list[dict[str, Any]]:
    """`ccrp vpn revoke`: revoke the robot's certificates, end its session, push the CRL."""
    from . import vpn

    return vpn.revoke(fleet, robot, cert, provider, say)


def snapshot_build(fleet, provider: Provider, say: Say, if_missing: bool = False, bare: bool = False):
    """`ccrp snapshot build`: the golden image from the recipe, recorded for new clones. With
    `if_missing`, the recorded one is kept while its image exists and holds the inventory's
    software."""
    from ..services.workloads import stale_snapshot

    with fleet.store.lock():
        recorded = fleet.store.load_state().snapshot or {}
        current = recorded.get("image")
        # Kept only while it holds the inventory's software (a changed workspace needs a new one).
        if if_missing and current and provider.has_image(current) and bool(recorded.get("bare")) == bare \
                and stale_snapshot(fleet, fleet.store.load_state()) is None:
            kept = [s for s in provider.list_snapshots() if s.id == recorded.get("id") or s.name == current]
            if kept:
                say(f"snapshot {current} exists; new clones start from it")
                return kept[0]
        return _build(fleet, provider, say, bare)


def _build(fleet, provider: Provider, say: Say, bare: bool = False):
    """Build the golden image, record it, drop the snapshots retention lets go (under the fleet lock)."""
    from . import snapshots

    record = snapshots.build(fleet, provider, say, bare=bare)
    snapshots.retain(fleet, provider, say)
    say(f"snapshot {record.name} recorded: new clones of fleet {fleet.name!r} start from it")
    return record


def snapshot_bake(fleet, provider: Provider, say: Say, base_image: str | None, timeout: float):
    """`ccrp snapshot bake`: a builder instance installs the recipe, is captured, then terminated."""
    from . import snapshots

    with fleet.store.lock():
        record = snapshots.bake(fleet, provider, say, base_image=base_image, timeout=timeout)
        snapshots.retain(fleet, provider, say)
    return record


def snapshot_create(fleet, provider: Provider, robot: str, use: bool):
    """`ccrp snapshot create`: capture a configured clone as a snapshot."""
    from . import snapshots

    with fleet.store.lock():
        return snapshots.create(fleet, provider, robot, use)


def snapshot_delete(fleet, provider: Provider, snapshot: str, force: bool) -> None:
    """`ccrp snapshot delete`."""
    from . import snapshots

    with fleet.store.lock():
        snapshots.delete(fleet, provider, snapshot, force)


def gc(fleet, provider: Provider, dry_run: bool, unlabelled: bool, say: Say) -> tuple[list, list]:
    """`ccrp gc`: the fleet's leaked resources, and on a host that keeps the snapshot images
    (Ability.HOST_IMAGES) the orphan images, deleted unless `dry_run`: (leaks, images)."""
    from .gc import collect, collect_images
    from ..errors import CcrpError
    from ..providers import Ability

    if not dry_run and not fleet.store.state_path.exists():
        # Without state every owned resource looks leaked: a wrong CCRP_HOME would wipe the fleet.
        raise CcrpError(f"no state for fleet {fleet.name!r} in {fleet.store.root}: everything would count as a leak",
                        hint="run where the fleet's state lives (CCRP_HOME), `ccrp gc --dry-run` to look, or `ccrp fleet down`")
    with fleet.store.lock():  # no `fleet up` may create clones while we decide what is a leak
        leaks = collect(fleet.store.load_state(), provider, dry_run, say, fleet.inventory.snapshots.keep)
        images = []
        if Ability.HOST_IMAGES in provider.abilities:  # snapshot images live on this host, whatever their state
            images = collect_images(cast("HostImages", provider), dry_run, unlabelled, say)
    return leaks, images


def ensure_pki(fleet, say: Say) -> None:
    """A new fleet's PKI is made by the first command that needs it, as `ccrp vpn init` would
    (which takes the fleet lock: call this before taking it)."""
    if fleet.pki.exists():
        return
    from . import vpn

    made = vpn.init(fleet)
    say(f"fleet {fleet.name!r} had no PKI yet: created its CA {made['ca']} (as `ccrp vpn init`)")


def ensure_snapshot(fleet, provider: Provider, say: Say, robots: list[str] | None = None) -> None:
    """A new Docker fleet's golden image is built by the first command that creates a clone, as
    `ccrp snapshot build` would (the caller holds the fleet lock). A cloud's is baked on purpose
    (`ccrp snapshot bake`: a builder instance, minutes, billed), so there the clone says so.
    The clones of `robots` (default: every member) are held against the quotas first: a host
    without room for them refuses before minutes of building (and a GB of libvirt pool)."""
    from .quotas import check_growth
    from ..providers import Ability

    recorded = fleet.store.load_state().snapshot or {}
    if Ability.LOCAL_BUILD not in provider.abilities or (recorded.get("image") and provider.has_image(recorded["image"])):
        return
    check_growth(fleet, provider, [r.name for r in fleet.members(fleet.load_allocated())] if robots is None else robots, say)
    say(f"fleet {fleet.name!r} has no snapshot yet: building it (as `ccrp snapshot build`)")
    _build(fleet, provider, say)


def robot_teleop(fleet, provider: Lifecycle, robot: str, linear: float, angular: float, topic: str = "cmd_vel",
                 timeout: float = 5.0, keep: bool = False) -> dict:
    """`ccrp robot teleop` and the dashboard's drive keys: one velocity command through the clone.
    No fleet lock: it changes nothing ccrp records, and an operator must not wait behind a scale."""
    from ..robot.evaluation import send_command

    return send_command(fleet, provider, robot, linear, angular, topic, timeout, keep)


def robot_power(fleet, robot: str, action: str, say: Say, timeout: float = 30) -> dict:
    """`ccrp robot power on|off|status` and the dashboard's Power buttons: through the robot's clone
    to its power device, waiting for its report. No fleet lock: ccrp records nothing (a first use
    on a simulated robot issues its device's certificate under the lock)."""
    from ..robot.power import power

    return power(fleet, robot, action, say, timeout)
