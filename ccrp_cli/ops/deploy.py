"""ccrp deploy (docs/workloads.md, Deploy): a changed workspace or `run` list onto running clones,
without re-creating them.

The workspace is built once, on this machine, in the clone image (the snapshot's Dockerfile with
the current software: Docker's layer cache runs only the software's layers), and its install
space (/opt/ccrp/workspace) read out of the image as a tar (providers.build_workspace, this host's
Docker engine whatever the fleet's backend). Where this machine has no Docker engine (or with
`--build-on clone`), one running clone of the deploy builds it in its own image, as a bake's
builder does (templates/image/software-bake.sh), beside its own install space (build_on_clone).
Every clone runs the same Debian 12 platform, so the same tar serves every backend. Each clone
gets it gzipped as a root-only file, and one fixed script (install_space.DEPLOY_SH, names and digests as argv words) unpacks it beside the current
one and swaps them; then the node units are brought in line (workloads.apply_nodes: only
those whose inputs changed restart) and each restarted unit must stay up (workloads.node_health,
the check `fleet up` makes too). A unit that does not is reported with its last journal lines, and
the clone goes back to the workspace and units it had: the previous version keeps running. Until
the check passed, the clone holds a pending mark: a deploy stopped before (Ctrl-C, killed) is
finished by the next one. Ctrl-C starts no further clone and puts those being changed back.
The install space pushed is kept in the fleet's state directory: a clone started or made later
gets it from `fleet up` (ops/clones.py). Each clone keeps the version the deploy replaced, which
`--rollback` puts back.

apt and pip packages are the snapshot's: a change of them needs a new snapshot and new clones.
"""

from __future__ import annotations

import io
import json
import re
import tarfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, cast

from . import install_space
from .clones import CloneResult, StateWriter
from .install_space import pushed, script
from ..errors import CcrpError, InputError
from ..fleet import Fleet
from ..models.software import Ready
from ..probe import same
from ..providers.base import CloneState
from ..render.files import BundleFile
from ..services.workloads import (
    INDEX,
    NO_SOFTWARE,
    DeployInputs,
    SnapshotSoftware,
    Stopped,
    absent_index,
    apply_nodes,
    is_secret,
    node_of,
    last_lines,
    node_health,
    ready_specs,
    packages_record,
    unit_name,
)

if TYPE_CHECKING:
    from ..models.inventory import Inventory
    from ..models.state import FleetState
    from ..providers.base import Provider, Reaches

Progress = Callable[[str], None]

MAX_INSTALL_BYTES = 256 << 20  # the install space's tar, pushed to every clone
NODE = re.compile(r"[a-z][a-z0-9-]*")  # a NodeName: what the clone's index may pass on to its scripts
# -- what each clone runs, and what would change --------------------------------------------------

@dataclass
class Change:
    """One clone: the software it runs (old) and the inventory's (new), its node files as they
    should be, the sha256 of those it holds, and the nodes that start, restart or stop."""

    robot: str
    old: str
    new: str
    files: list[BundleFile]
    have: dict[str, str]
    # ./PATH -> (sha256, octal mode) of each file of the clone's install space: deploy sends only
    # the others (install_space.delta).
    on_clone: dict[str, tuple[str, str]]
    start: list[str] = field(default_factory=list)
    restart: list[str] = field(default_factory=list)
    stop: list[str] = field(default_factory=list)
    # The secrets (<node>/<NAME>, never a value) the clone lacks or holds with other content.
    secrets: list[str] = field(default_factory=list)
    # A deploy stopped before its check left the clone so (DEPLOY_SH's D/pending: nodes, swapping,
    # swapped), "" when none did; `running` are the nodes its index names.
    pending: str = ""
    running: list[str] = field(default_factory=list)

    @property
    def workspace(self) -> bool:
        return self.old != self.new

    @property
    def nodes_current(self) -> bool:
        if not self.files:
            return INDEX not in self.have  # none wanted: current once none is there
        return same(self.have, self.files)

    @property
    def current(self) -> bool:
        return not self.workspace and self.nodes_current

    @property
    def unsettled(self) -> bool:
        """A deploy left the clone unchecked with other software than the inventory's (or in the
        middle of its swap): it goes back before anything else."""
        return bool(self.pending) and (self.pending == "swapping" or not self.current)

    def summary(self) -> str:
        if self.pending and not self.unsettled:
            return f"{STOPPED_BEFORE}: check its nodes ({', '.join(self.running) or 'none'})"
        parts = [f"workspace {self.old} -> {self.new}"] if self.workspace else [f"workspace {self.new} (unchanged)"]
        if self.unsettled:
            parts.insert(0, f"roll back {STOPPED_BEFORE}, then (as now)")
        for word, names in (("start", self.start), ("restart", self.restart), ("stop", self.stop)):
            if names:
                parts.append(f"{word} {', '.join(names)}")
        if self.secrets:
            parts.append(f"secret{'s' * (len(self.secrets) > 1)} {', '.join(self.secrets)} changed")
        return "; ".join(parts)


def probe(inputs: DeployInputs, provider: Reaches, state: FleetState, robot: str) -> Change:
    """What robot's clone runs (one round trip) against the inventory's software and nodes."""
    new, files = inputs.digest, inputs.nodes[robot]
    probed = files or [absent_index()]
    # Files pushed to the clone: each has its dest.
    out = script(provider, robot, "probe", *(cast(str, f.dest) for f in probed), timeout=30)
    _, _, rest = out.partition("== current\n")
    current, _, rest = rest.partition("\n== index\n")
    index_text, _, rest = rest.partition("\n== pending\n")
    pending, _, rest = rest.partition("\n== digests\n")
    digests, _, listing = rest.partition("\n== workspace\n")
    have = {line.split()[1]: line.split()[0] for line in digests.splitlines() if len(line.split()) == 2}
    try:
        index = json.loads(index_text) if index_text.strip() else {}
    except ValueError:
        index = {}
    old_nodes = index.get("nodes", {}) if isinstance(index, dict) else {}
    # The clone's workspace: the digest deploy last wrote, else the one its units were made with
    # (its snapshot's), else what state says.
    rec = state.robots[robot]
    old = (current.strip() or (index.get("software") if isinstance(index, dict) else None)
           or rec.software or (state.snapshot or {}).get("software", NO_SOFTWARE))
    new_nodes = json.loads(files[-1].content)["nodes"] if files else {}
    # A changed secret restarts its node: its content is in no digest of the index, only in its
    # file's, which the probe compared.
    secrets = [f for f in files if is_secret(f) and not same(have, [f])]
    resecret = {node_of(f) for f in secrets}
    return Change(robot, str(old), new, files, have, workspace_files(listing),
                  start=[n for n in new_nodes if n not in old_nodes],
                  restart=[n for n in new_nodes if n in old_nodes and (old_nodes[n] != new_nodes[n] or n in resecret)],
                  stop=[n for n in old_nodes if n not in new_nodes], secrets=[f.name for f in secrets],
                  pending=pending.strip(), running=[n for n in old_nodes if isinstance(n, str) and NODE.fullmatch(n)])


def workspace_files(listing: str) -> dict[str, tuple[str, str]]:
    """The probe's list of the clone's install space: `sha256  ./PATH` lines, then `== modes` and
    `MODE ./PATH` lines. A name sha256sum escaped (a backslash first: a newline in it) is left out,
    so that file is sent."""
    sums, _, modes = listing.partition("== modes\n")
    digest = {line[66:]: line[:64] for line in sums.splitlines() if len(line) > 66 and line[64:66] == "  "}
    mode: dict[str, str] = {}
    for line in modes.splitlines():
        bits, _, path = line.partition(" ")
        mode[path] = bits
    return {path: (digest[path], mode[path]) for path in digest if path in mode}


# -- which clones -----------------------------------------------------------------------------------

def targets(fleet: Fleet, state: FleetState, robot: str | None, type_: str | None) -> list[str]:
    """The robots --robot / --type name (every member without them); unknown ones: exit 2."""
    members = fleet.members(state)
    if robot is not None and type_ is not None:
        raise InputError("give --robot or --type, not both")
    if robot is not None:
        return [fleet.robot(state, robot).name]
    if type_ is not None:
        picked = [r.name for r in members if r.type == type_]
        if not picked:
            types = sorted({r.type for r in members})
            raise InputError(f"no robot of fleet {fleet.name!r} has type {type_!r}", hint=f"types: {', '.join(types) or 'none'}")
        return picked
    return [r.name for r in members]


def check_packages(state: FleetState, robots: list[str], software: SnapshotSoftware) -> None:
    """Refuse (before anything) when the inventory's apt/pip packages are not those each clone's
    snapshot holds: deploy changes the workspace and the nodes, never the packages."""
    want = packages_record(software)
    snap = state.snapshot or {}
    for robot in robots:
        rec = state.robots.get(robot)
        if rec is None or not rec.provider_id:
            continue
        have = rec.packages or (snap.get("packages") if rec.image and rec.image in (snap.get("id"), snap.get("image")) else None)
        if have is None:
            if rec.software == software.digest:
                continue  # the digest covers the packages: the same ones
            raise InputError(f"robot {robot!r}'s clone does not record the apt/pip packages its snapshot holds "
                             "(made before ccrp deploy)", hint="build a new snapshot and re-create the clones")
        if have != want:
            raise InputError(f"the inventory's apt/pip packages are not those robot {robot!r}'s clone has "
                             f"({_package_diff(have, want)}): deploy changes the workspace and the nodes only",
                             hint="build a new snapshot and re-create the clones (ccrp snapshot build, then "
                                  "ccrp clone delete and ccrp clone create)")


def _package_diff(have: str, want: str) -> str:
    try:
        old, new = json.loads(have), json.loads(want)
    except ValueError:
        return "unreadable record"
    parts = []
    if old.get("distro") != new.get("distro"):
        parts.append(f"distro {old.get('distro')} -> {new.get('distro')}")
    for kind in ("apt", "pip"):
        added = [p for p in new.get(kind, []) if p not in old.get(kind, [])]
        gone = [p for p in old.get(kind, []) if p not in new.get(kind, [])]
        parts += [f"{kind} + {p}" for p in added] + [f"{kind} - {p}" for p in gone]
    return ", ".join(parts[:6]) + (", ..." if len(parts) > 6 else "") or "reordered"


# -- the build --------------------------------------------------------------------------------------

BUILD_ON = ("auto", "local", "clone")
CLONE_BUILD_OUT = "/var/lib/ccrp/deploy-build.tgz"  # on the clone a deploy builds on, until read back
CLONE_BUILD_TIMEOUT = 1800.0


def builder(provider: Provider, build_on: str, live: list[str]) -> str | None:
    """Where the install space is built: None for this host's Docker engine, else the robot whose
    running clone builds it (`auto`: the first of `live` when no engine answers here)."""
    from ..providers import local_engine_answers

    if build_on == "local" or (build_on == "auto" and local_engine_answers()):
        return None
    if not live:
        why = "this host has no Docker engine, and" if build_on == "auto" else "--build-on clone:"
        raise CcrpError(f"{why} no clone of this deploy is running to build the workspace on",
                        hint="start one (`ccrp clone start --robot R`), or install Docker here")
    return live[0]


def build_on_clone(provider: Reaches, robot: str, software: SnapshotSoftware, progress: Progress) -> bytes:
    """The install space's tar built on robot's running clone, in its own image: the workspace's
    sources pushed, templates/image/software-bake.sh building under a root of its own (the clone's
    install space and nodes untouched; apt and pip are the snapshot's, as deploy checked), the
    result read back and removed."""
    import base64
    import binascii
    import gzip

    from .snapshots import run_software_script, software_env

    t0 = time.monotonic()
    progress(f"building workspace {software.digest} on robot {robot!r}'s clone, in its image")
    env = software_env(software) | {"CCRP_APT": "", "CCRP_PIP": "", "CCRP_LOGIN": "", "CCRP_OUT": CLONE_BUILD_OUT}
    run_software_script(provider, robot, software, env, f"robot {robot!r}'s clone", CLONE_BUILD_TIMEOUT)
    rc, out = provider.transport.exec(robot, ["sh", "-c", 'base64 -w0 "$0" && rm -f "$0"', CLONE_BUILD_OUT], timeout=300)
    try:
        data = gzip.decompress(base64.b64decode(out.strip(), validate=True)) if rc == 0 else None
    except (ValueError, binascii.Error, OSError, EOFError):
        data = None
    if data is None:
        raise CcrpError(f"the install space built on robot {robot!r}'s clone could not be read back: {out.strip()[-200:]}")
    progress(f"workspace {software.digest} built on robot {robot!r}'s clone after {time.monotonic() - t0:.0f} s "
             f"({len(data) >> 10} kB)")
    return data


def build_install_space(inv: Inventory, software: SnapshotSoftware, progress: Progress,
                        provider: Reaches | None = None, on: str | None = None) -> bytes:
    """The tar of the install space (top directory `workspace/`) built from `software` in the
    fleet's clone image: on this host's Docker engine whatever the fleet's backend, or on robot
    `on`'s running clone (build_on_clone)."""
    from ..providers import build_workspace
    from ..services.registry import image_agents

    if software.build_type is None:  # no workspace (any more): an empty install space
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w") as tar:
            info = tarfile.TarInfo("workspace")
            info.type, info.mode = tarfile.DIRTYPE, 0o755
            tar.addfile(info)
        return buf.getvalue()
    # In the snapshot's own image (its agents too), so the build finds the snapshot's layers cached.
    if on is not None and provider is not None:
        data = build_on_clone(provider, on, software, progress)
    else:
        data = build_workspace(inv, software, image_agents(), progress)
    if len(data) > MAX_INSTALL_BYTES:
        raise CcrpError(f"the workspace's install space is {len(data) >> 20} MB, more than deploy pushes "
                        f"({MAX_INSTALL_BYTES >> 20} MB)", hint="build a new snapshot and re-create the clones")
    return data


# -- on each clone ----------------------------------------------------------------------------------

STOPPED_BEFORE = "a deploy stopped before its check"  # what a clone's pending mark is, in results


def apply(provider: Reaches, writer: StateWriter, change: Change, tar: bytes | None, progress: Progress,
          stop: threading.Event | None = None, reprobe: Callable[[], Change] | None = None) -> CloneResult:
    """Bring one clone to the inventory's software and nodes; back to what it ran if a restarted
    node fails its health check. A deploy stopped before its check on this clone (its pending mark)
    is finished first: checked and committed when it brought the inventory's software, else rolled
    back (then `reprobe` says what the clone runs). `stop` set (Ctrl-C): a clone being changed goes
    back as it was, its result `interrupted`. `tar`: the install space built, of which the clone
    is sent what it lacks (the whole of it if that delta does not unpack)."""
    t0 = time.monotonic()
    robot = change.robot
    took = lambda: time.monotonic() - t0  # noqa: E731
    note = ""
    if change.unsettled:
        # Never checked, and not what the inventory wants: back to the version before it first.
        ok, back = _rollback(provider, robot, change.running)
        if not ok:
            return _result(progress, robot, "failed", f"{STOPPED_BEFORE}: {back}", took())
        assert reprobe is not None
        change, note = reprobe(), f"{STOPPED_BEFORE} rolled back; "
        progress(f"[{robot}] {note}{back}")
    elif change.pending:
        # The inventory's software, left unchecked: the check the stopped deploy did not make.
        try:
            failing = node_health(provider, robot, change.running, stop, ready_specs(change.files))
        except Stopped:
            return _result(progress, robot, "interrupted", f"{STOPPED_BEFORE}, left for the next deploy to check", took())
        if failing is not None:
            return _failed(provider, robot, failing, change.running, f"after {STOPPED_BEFORE}", progress, took)
        _quietly(lambda: script(provider, robot, "commit"))
        writer.update(robot, software=change.new)
        return _result(progress, robot, "deployed", f"{STOPPED_BEFORE} finished: its nodes stay up; software {change.new}",
                       took())
    if change.current:
        if writer.state.robots[robot].software != change.new:  # state lost track: the clone says
            writer.update(robot, software=change.new)
        if note:
            return _result(progress, robot, "deployed", f"{note}software {change.new}", took())
        return CloneResult(robot, "current", f"software {change.new}", took())
    if change.workspace and tar is None:  # the clone went back to a workspace this run did not build
        return _result(progress, robot, "failed", f"{note}its workspace differs: ccrp deploy again", took())
    sent = 0

    def stage(space: bytes, *how: str) -> None:
        nonlocal sent
        payload = pushed(space)
        install_space.push(provider, robot, change.new, payload)
        sent += len(payload)
        script(provider, robot, "stage", change.new, *how)

    try:
        if not change.workspace:
            script(provider, robot, "stage", "-")
        elif change.on_clone:
            try:
                stage(install_space.delta(cast(bytes, tar), change.on_clone), "delta")
            except CcrpError as exc:  # a path that changed kind (a directory now a file): the whole space
                progress(f"[{robot}] the changed files did not unpack ({exc.message[-200:]}): sending the whole install space")
                stage(cast(bytes, tar))
        else:
            stage(cast(bytes, tar))
    except CcrpError:
        _quietly(lambda: script(provider, robot, "stage-clean"))  # nothing was swapped: only the staging goes
        raise
    changed, restarted = False, []
    try:
        _check(stop)
        # From here the clone holds its pending mark until commit or rollback (DEPLOY_SH).
        changed = True
        if change.workspace:
            script(provider, robot, "swap", change.new)
        else:
            script(provider, robot, "begin")
        _check(stop)
        # A changed workspace changes every node's digest (it is one of their inputs): all restart.
        restarted = apply_nodes(provider, robot, change.files, change.have)
        failing = node_health(provider, robot, restarted, stop, ready_specs(change.files))
    except BaseException as exc:
        if changed:
            back = _rollback(provider, robot, restarted or change.start + change.restart)[1]
        else:
            _quietly(lambda: script(provider, robot, "stage-clean"))
            back = "nothing changed"
        if isinstance(exc, Stopped):
            return _result(progress, robot, "interrupted", f"{note}{back}", took())
        if not isinstance(exc, Exception):
            raise  # a Ctrl-C in this thread: the clone is back as it was; the interruption goes on
        why = exc.one_line() if isinstance(exc, CcrpError) else f"{type(exc).__name__}: {exc}"
        raise CcrpError(f"{note}{why}; {back}") from None
    if failing is not None:
        return _failed(provider, robot, failing, restarted, f"{note}after the deploy", progress, took)
    _quietly(lambda: script(provider, robot, "commit"))
    writer.update(robot, software=change.new)
    result = _result(progress, robot, "deployed", note + change.summary() + (f"; sent {_size(sent)}" if sent else ""),
                     took())
    result.sent_bytes = sent
    return result


def _size(n: int) -> str:
    return f"{n / 1e6:.1f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"


def _check(stop: threading.Event | None) -> None:
    if stop is not None and stop.is_set():
        raise Stopped()


def _result(progress: Progress, robot: str, action: str, detail: str, seconds: float) -> CloneResult:
    progress(f"[{robot}] {action}: {detail}")
    return CloneResult(robot, action, detail, seconds)


def _failed(provider: Reaches, robot: str, failing: tuple[str, str], restart: list[str], when: str,
            progress: Progress, took: Callable[[], float]) -> CloneResult:
    """A node failed its check: its last lines read, then the clone rolled back."""
    unit, why = failing
    lines = last_lines(provider, robot, unit)
    back = _rollback(provider, robot, restart)[1]
    return _result(progress, robot, "failed", f"{unit} {why} {when}; {back}; its last lines: {lines}", took())


def _rollback(provider: Reaches, robot: str, restart: list[str]) -> tuple[bool, str]:
    """DEPLOY_SH's rollback, `restart` the nodes restarted on the version going away: whether it
    went through, and what to say. It tries every step, so a failed one leaves the others done."""
    try:
        script(provider, robot, "rollback", *restart)
        return True, "rolled back: the previous version runs"
    except CcrpError as exc:
        return False, (f"the rollback did not go through ({exc.message}): "
                       f"ccrp clone exec --robot {robot} -- systemctl status 'ccrp-run-*'")


def _quietly(fn: Callable[[], object]) -> None:
    try:
        fn()
    except CcrpError:
        pass  # tidying up only: the clone runs what it should


# -- deploy --rollback: the version each clone keeps ----------------------------------------------------

@dataclass
class Kept:
    """What robot's clone keeps for `deploy --rollback` (DEPLOY_SH's D/last): the software digest,
    the nodes and their readiness of the version the last deploy replaced; `digest` None when it
    keeps none. `running`: the digest it runs now."""

    robot: str
    digest: str | None
    nodes: list[str]
    ready: dict[str, Ready]
    running: str
    pending: str

    def summary(self) -> str:
        nodes = f"nodes {', '.join(self.nodes)}" if self.nodes else "no nodes"
        return f"software {self.running} -> {self.digest}; {nodes}"


def kept(provider: Reaches, state: FleetState, robot: str) -> Kept:
    """The version robot's clone keeps (one round trip)."""
    out = script(provider, robot, "last", timeout=30)
    _, _, rest = out.partition("== digest\n")
    digest, _, rest = rest.partition("\n== index\n")
    index_text, _, rest = rest.partition("\n== pending\n")
    pending, _, current = rest.partition("\n== current\n")
    try:
        index = json.loads(index_text) if index_text.strip() else {}
    except ValueError:
        index = {}
    index = index if isinstance(index, dict) else {}
    snapshot = (state.snapshot or {}).get("software", NO_SOFTWARE)
    running = current.strip() or state.robots[robot].software or snapshot
    if digest.strip() == "-":
        return Kept(robot, None, [], {}, str(running), pending.strip())
    # No digest: the kept version ran the software its units were made with (its snapshot's).
    was = digest.strip() or index.get("software") or snapshot
    nodes = [n for n in index.get("nodes", {}) if isinstance(n, str) and NODE.fullmatch(n)]
    ready = {n: Ready.model_validate(r) for n, r in (index.get("ready") or {}).items() if n in nodes}
    return Kept(robot, str(was), nodes, ready, str(running), pending.strip())


def restore(provider: Reaches, writer: StateWriter, keep: Kept, progress: Progress,
            stop: threading.Event | None = None) -> CloneResult:
    """Put the kept version back on one clone as a deploy would (its nodes restarted and checked,
    back to the version it ran if one fails); the version it leaves becomes the kept one."""
    t0 = time.monotonic()
    robot, took = keep.robot, lambda: time.monotonic() - t0
    if keep.pending:
        return _result(progress, robot, "failed", f"{STOPPED_BEFORE}: ccrp deploy first (it finishes or undoes it)",
                       took())
    changed = False
    try:
        script(provider, robot, "restore")
        changed = True
        _check(stop)
        if keep.nodes:
            rc, out = provider.transport.exec(robot, ["systemctl", "restart", *(unit_name(n) for n in keep.nodes)],
                                              timeout=120)
            if rc != 0:
                raise CcrpError(f"the kept nodes did not start: {' '.join(out.split())[-300:]}")
        failing = node_health(provider, robot, keep.nodes, stop, keep.ready)
    except BaseException as exc:
        back = _rollback(provider, robot, keep.nodes)[1] if changed else "nothing changed"
        if isinstance(exc, Stopped):
            return _result(progress, robot, "interrupted", back, took())
        if not isinstance(exc, Exception):
            raise
        why = exc.one_line() if isinstance(exc, CcrpError) else f"{type(exc).__name__}: {exc}"
        raise CcrpError(f"{why}; {back}") from None
    if failing is not None:
        return _failed(provider, robot, failing, keep.nodes, "after the rollback", progress, took)
    _quietly(lambda: script(provider, robot, "commit"))
    writer.update(robot, software=keep.digest)
    return _result(progress, robot, "rolled back", keep.summary(), took())


# -- the command --------------------------------------------------------------------------------------

def _running(provider: Provider, names: list[str], robot: str | None) -> tuple[list[str], dict[str, CloneResult], set[str]]:
    """The targets whose clone runs, a result for each other (one robot asked for by name must be
    reachable; in a whole fleet, a stopped clone is not a failure), and the robots that have a clone."""
    existing = provider.query()
    running = {n for n, rec in existing.items() if rec.state is CloneState.RUNNING}
    results = {name: CloneResult(name, "failed" if robot else "skipped",
                                 "no running clone: ccrp fleet up (or ccrp clone start) first")
               for name in names if name not in running}
    return [n for n in names if n in running], results, set(existing)


def rollback(fleet: Fleet, provider: Provider, progress: Progress, robot: str | None = None,
             type_: str | None = None, dry_run: bool = False, max_parallel: int | None = None) -> list[CloneResult]:
    """`ccrp deploy --rollback`: each target clone back to the version its last deploy replaced
    (the caller holds the fleet lock unless dry_run). A clone that keeps none (never deployed to)
    fails when named, else is skipped."""
    from .reconcile import _fan_out

    state = fleet.store.load_state()
    names = targets(fleet, state, robot, type_)
    live, results, _ = _running(provider, names, robot)
    found: dict[str, Kept] = {}
    stop = threading.Event()

    def look(name: str) -> CloneResult:
        found[name] = kept(provider, state, name)
        return CloneResult(name, "probed")

    for r in _fan_out(look, live, progress, provider, stop):
        if r.action == "failed":
            results[r.robot] = r
    for name, keep in found.items():
        if keep.digest is None:
            results[name] = CloneResult(name, "failed" if robot else "skipped",
                                        "no previous version is kept on this clone (no deploy has changed it)")
        elif dry_run:
            results[name] = CloneResult(name, "would roll back", keep.summary())
    if dry_run:
        return [results[n] for n in names]
    todo = [n for n in live if n in found and n not in results]
    writer = StateWriter(fleet, state)
    for r in _fan_out(lambda n: restore(provider, writer, found[n], progress, stop), todo, progress, provider, stop,
                      max_parallel):
        results[r.robot] = r
    return [results[n] for n in names]


def deploy(fleet: Fleet, provider: Provider, progress: Progress, robot: str | None = None, type_: str | None = None,
           dry_run: bool = False, canary: int = 0, max_parallel: int | None = None,
           build_on: str = "auto") -> list[CloneResult]:
    """`ccrp deploy`: the caller holds the fleet lock unless dry_run. `canary` clones first (in
    the fleet's order): when one of them fails, no other is changed. `max_parallel`: at most that
    many clones changed at once. `build_on` (BUILD_ON): where the workspace is built (builder).
    Ctrl-C: no further clone is started, those being changed go back
    as they were, each robot's line says which (then the interruption goes on)."""
    from .reconcile import _fan_out

    state = fleet.store.load_state()
    names = targets(fleet, state, robot, type_)
    inputs = DeployInputs.read(fleet, state, names)  # read and checked before anything
    live, results, existing = _running(provider, names, robot)
    # The clones there are (a robot whose clone failed and went has none: fleet up makes it anew).
    check_packages(state, [n for n in names if n in existing], inputs.software)
    changes: dict[str, Change] = {}
    stop = threading.Event()  # set by _fan_out on Ctrl-C: the pool's threads never see it

    def look(name: str) -> CloneResult:
        changes[name] = probe(inputs, provider, state, name)
        return CloneResult(name, "probed")

    for r in _fan_out(look, live, progress, provider, stop):
        if r.action == "failed":
            results[r.robot] = r
    # A stopped clone gets the deployed software when it starts (ops/clones.py), from the install
    # space kept in the state directory: it is built for it too.
    digest = inputs.software.digest
    waiting = [n for n in results if n in existing and state.robots[n].software != digest]
    for name in waiting:
        results[name] = CloneResult(name, "skipped", f"not running: gets software {digest} when it starts "
                                                     "(ccrp clone start, or fleet up)")
    if dry_run:
        for name, ch in changes.items():
            quiet = ch.current and not ch.pending
            results[name] = CloneResult(name, "current" if quiet else "would deploy",
                                        f"software {ch.new}" if quiet else ch.summary())
        return [results[n] for n in names]
    tar = None
    # A clone rolled back from a stopped deploy may then need the workspace.
    if any(ch.workspace or ch.unsettled for ch in changes.values()) or (
            waiting and install_space.saved(fleet, digest) is None):
        # One build for every clone; a failure leaves every clone as it was.
        on = builder(provider, build_on, live) if inputs.software.build_type is not None else None
        tar = build_install_space(inputs.inventory, inputs.software, progress, provider, on)
    writer = StateWriter(fleet, state)
    if tar is not None:
        install_space.save(fleet, digest, pushed(tar))
        with writer.lock:
            state.deployed = digest
            fleet.store.save_state(state)
    todo = [n for n in live if n in changes]

    def one(name: str) -> CloneResult:
        return apply(provider, writer, changes[name], tar, progress, stop,
                     lambda: probe(inputs, provider, state, name))

    # The canaries are the first clones with something to change: a clone already current proves nothing.
    changing = [n for n in todo if not (changes[n].current and not changes[n].pending)]
    first = changing[:canary] if canary else []
    rest = [n for n in todo if n not in first]
    for r in _fan_out(one, first, progress, provider, stop, max_parallel):
        results[r.robot] = r
    if failed := [n for n in first if results[n].action != "deployed"]:
        why = f"canary {', '.join(failed)} did not deploy: no other clone changed"
        progress(f"{why} (ccrp deploy again once it is fixed)")
        for name in [n for n in rest if n in changing]:
            results[name] = CloneResult(name, "not started", why)
        rest = [n for n in rest if n not in changing]  # the clones already current say so
    for r in _fan_out(one, rest, progress, provider, stop, max_parallel):
        results[r.robot] = r
    return [results[n] for n in names]
