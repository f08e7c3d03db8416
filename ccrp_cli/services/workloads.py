"""The robot's own software on its clone (docs/workloads.md): the workspace's packages and what
they depend on, the digest a snapshot carries, each clone's node units, their state and logs.

The snapshot holds the software (packages, the built workspace); `fleet up` gives each clone the
units of its robot's `run` nodes and starts them. Every name that reaches a unit or a command line
is a NodeName ([a-z][a-z0-9-]*); a node's argv is escaped for systemd, never given to a shell.
"""

from __future__ import annotations

import hashlib
import json
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import CcrpError, InputError, shown
from ..models.inventory import Inventory, Robot
from ..models.software import RunNode, Software
from ..render.files import BundleFile
from . import programs
from .base import CloneService, ServiceContext

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..models.state import FleetState
    import threading

    from ..providers.base import Reaches

UNIT_DIR = "/etc/systemd/system"
UNIT_PREFIX = "ccrp-run-"
INDEX = "/etc/ccrp/workloads.json"  # the nodes ccrp put on this clone, with their digests
ROS_RUN = "/usr/local/lib/ccrp/ros-run"
NO_SOFTWARE = "none"  # the digest of a snapshot (or inventory) without software of the user's

# Directories of a workspace that are build output, not source (catkin, colcon) or tool state.
SKIP_DIRS = {"build", "devel", "install", "log", "logs", "__pycache__", ".git", ".hg", ".svn"}
MAX_WORKSPACE_BYTES = 64 << 20  # goes into a build context (Docker) or over SSH (clouds)
SAFE_PATH = re.compile(r"[A-Za-z0-9._+/-]{1,200}")
DEPEND_TAGS = ("depend", "build_depend", "exec_depend", "run_depend", "buildtool_depend", "build_export_depend",
               "test_depend")


def unit_name(node: str) -> str:
    return f"{UNIT_PREFIX}{node}.service"


# -- the workspace ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Package:
    name: str
    build_type: str  # catkin | ament_python | ament_cmake | cmake
    depends: tuple[str, ...]  # rosdep keys, the workspace's own packages left out
    path: str  # package.xml, relative to the workspace


def workspace_dir(inv_path: Path | None, software: Software) -> Path | None:
    if software.workspace is None:
        return None
    base = (inv_path.parent if inv_path is not None else Path.cwd()).resolve()
    path = (base / software.workspace).resolve()
    # Resolved, the workspace stays in the inventory's directory, as its text must (models/software.py):
    # it is read whole into the snapshot, where the workspace's own code runs, so a link (`ws -> ~`)
    # must not pull the operator's home, keys and all, into the build.
    if not path.is_relative_to(base):
        raise InputError(f"software.workspace {shown(software.workspace)} leads out of the inventory's directory "
                         f"(to {shown(str(path), 200)})",
                         hint="put the workspace itself in the inventory's directory (or the inventory beside it), not a link to it")
    if not path.is_dir():
        raise InputError(f"software.workspace {shown(software.workspace)}: no directory {path}",
                         hint="give the workspace's directory (holding src/) relative to the inventory")
    return path


def workspace_files(root: Path) -> list[tuple[str, bytes]]:
    """(relative path, content) of the workspace's source files, sorted: what a snapshot builds and
    its digest covers. Build output, version control and symlinks leaving the workspace stay out."""
    out: list[tuple[str, bytes]] = []
    total = 0
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(part in SKIP_DIRS or part.startswith(".") for part in rel.parts):
            continue
        if path.is_symlink() and not path.resolve().is_relative_to(root):
            raise InputError(f"workspace file {rel} links outside the workspace ({path.resolve()})")
        if not path.is_file():
            continue
        data = path.read_bytes()
        total += len(data)
        if total > MAX_WORKSPACE_BYTES:
            raise InputError(f"workspace {root} holds more than {MAX_WORKSPACE_BYTES >> 20} MB of source",
                             hint="keep data and build output out of it (build/, install/, log/ are skipped)")
        out.append((rel.as_posix(), data))
    return out


def scan_packages(root: Path, files: list[tuple[str, bytes]]) -> list[Package]:
    import xml.etree.ElementTree as ET  # here: `ccrp status` imports this module and parses no package

    # A directory holding CATKIN_IGNORE or COLCON_IGNORE is left out with everything under it.
    ignored = [rel.rsplit("/", 1)[0] + "/" if "/" in rel else "" for rel, _ in files
               if rel.rsplit("/", 1)[-1] in ("CATKIN_IGNORE", "COLCON_IGNORE")]
    manifests = [(rel, data) for rel, data in files if rel.rsplit("/", 1)[-1] == "package.xml"
                 and not any(rel.startswith(prefix) for prefix in ignored)]
    if not manifests:
        raise InputError(f"workspace {root} holds no package.xml", hint="a ROS workspace has its packages under src/")
    parsed = []
    for rel, data in manifests:
        try:
            tree = ET.fromstring(data)
        except ET.ParseError as exc:
            raise InputError(f"workspace {root}: {rel} is not valid XML ({exc})") from None
        name = (tree.findtext("name") or "").strip()
        if not name:
            raise InputError(f"workspace {root}: {rel} names no package")
        keys = [(e.text or "").strip() for tag in DEPEND_TAGS for e in tree.findall(tag)]
        tools = [(e.text or "").strip() for e in tree.findall("buildtool_depend")]
        build_type = (tree.findtext("export/build_type") or "").strip() or ("catkin" if "catkin" in tools else "cmake")
        parsed.append((name, build_type, keys, rel))
    for _, _, _, rel in parsed:  # a package's directory becomes a word of the snapshot's build
        if not SAFE_PATH.fullmatch(rel):
            raise InputError(f"workspace {root}: package path {shown(rel)} has characters other than letters, digits and ._+-/",
                             hint="rename the package's directory")
    own = {name for name, *_ in parsed}
    return [Package(name, bt, tuple(dict.fromkeys(k for k in keys if k and k not in own)), rel)
            for name, bt, keys, rel in parsed]


# -- what the packages depend on --------------------------------------------------------------------

@dataclass
class Resolved:
    apt: list[str] = field(default_factory=list)
    pip: list[str] = field(default_factory=list)


def resolve(distro: str, packages: list[Package]) -> Resolved:
    """Each package.xml key to the Debian packages (ROS 1: Debian's ROS) or wheels (ROS 2) the
    recipe's `rosdep:` table names; a key with no entry is an error naming it and its package."""
    from ..recipes import is_ros2, recipe

    table = recipe(distro).rosdep
    out = Resolved()
    for pkg in packages:
        if is_ros2(distro) and pkg.build_type != "ament_python":
            raise InputError(f"package {shown(pkg.name)} ({pkg.path}) is {shown(pkg.build_type)}: a ROS 2 workspace here builds "
                             "ament_python packages only (the ROS 2 wheels have no rclcpp)")
        if not is_ros2(distro) and pkg.build_type != "catkin":
            raise InputError(f"package {shown(pkg.name)} ({pkg.path}) is {shown(pkg.build_type)}: a ROS 1 workspace builds catkin packages")
        for key in pkg.depends:
            if key in ("rclcpp", "rclcpp_components", "ament_cmake") and is_ros2(distro):
                raise InputError(f"package {shown(pkg.name)} depends on {key}: the ROS 2 wheels have no rclcpp (C++); "
                                 "write the node in Python (rclpy)")
            entry = table.get(key)
            if entry is None:
                raise InputError(f"package {shown(pkg.name)} depends on {shown(key)}, which resolves to no "
                                 f"{'wheel' if is_ros2(distro) else 'Debian package'} for {distro}",
                                 hint="add what it needs under software.apt or software.pip, and remove the key "
                                      "from package.xml, or name a key of the recipe's rosdep table")
            out.apt += [p for p in entry.apt if p not in out.apt]
            out.pip += [p for p in entry.pip if p not in out.pip]
    return out


# -- what a snapshot holds ----------------------------------------------------------------------------

@dataclass
class SnapshotSoftware:
    """The fleet's software as its snapshot holds it: the spec, the workspace and its packages,
    what they resolve to, and the digest of all of it."""

    spec: Software
    distro: str
    workspace: list[tuple[str, bytes]] = field(default_factory=list)
    packages: list[Package] = field(default_factory=list)
    resolved: Resolved = field(default_factory=Resolved)

    @property
    def empty(self) -> bool:
        return not (self.spec.apt or self.spec.pip or self.workspace)

    @property
    def apt(self) -> list[str]:
        return list(dict.fromkeys([*self.spec.apt, *self.resolved.apt]))

    @property
    def pip(self) -> list[str]:
        return list(dict.fromkeys([*self.spec.pip, *self.resolved.pip]))

    @property
    def build_type(self) -> str | None:
        return self.packages[0].build_type if self.packages else None

    @property
    def pip_install(self) -> list[str]:
        """What pip installs: the requirements, and `wheel` for ament_python packages (it builds
        them in the venv, whose setuptools has no bdist_wheel of its own)."""
        return self.pip + (["wheel"] if self.build_type == "ament_python" else [])

    @property
    def digest(self) -> str:
        if self.empty:
            return NO_SOFTWARE
        h = hashlib.sha256(json.dumps({"apt": self.apt, "pip": self.pip, "distro": self.distro}).encode())
        for rel, data in self.workspace:
            h.update(f"\0{rel}\0{len(data)}\0".encode())
            h.update(data)
        return h.hexdigest()[:16]


def packages_record(software: SnapshotSoftware) -> str:
    """What a snapshot holds that `ccrp deploy` cannot change on its clones (the Debian packages
    and wheels, for one distro), as state.json records it: deploy compares it with the inventory's."""
    return json.dumps({"distro": software.distro, "apt": software.apt, "pip": software.pip}, separators=(",", ":"))


def snapshot_software(inv: Inventory, inv_path: Path | None) -> SnapshotSoftware:
    """Read and check everything the snapshot will hold, before anything is built or changed."""
    spec = inv.snapshot_software()
    out = SnapshotSoftware(spec=spec, distro=inv.ros.distro)
    root = workspace_dir(inv_path, spec)
    if root is not None:
        out.workspace = workspace_files(root)
        out.packages = scan_packages(root, out.workspace)
        out.resolved = resolve(inv.ros.distro, out.packages)
    programs.check(inv, out.apt, out.workspace)  # a node whose program the clone lacks: refused here
    return out


def stale_snapshot(fleet: Fleet, state: FleetState, want: str | None = None) -> str | None:
    """Why the fleet's snapshot cannot serve the inventory's software (None when it can). `want`:
    the inventory's digest when the caller has it (reading it hashes the whole workspace)."""
    want = want or snapshot_software(fleet.inventory, fleet.path).digest
    have = (state.snapshot or {}).get("software", NO_SOFTWARE)
    if want == have:
        return None
    return (f"the snapshot holds software {have}, the inventory's is {want}" if want != NO_SOFTWARE
            else f"the snapshot holds software {have}, the inventory names none")


def check_snapshot(fleet: Fleet, state: FleetState, provider_kind: str) -> None:
    """Refuse to create or update clones whose snapshot lacks the inventory's software."""
    why = stale_snapshot(fleet, state)
    if why is not None and state.snapshot:
        from ..providers import Ability, info

        hint = f"ccrp snapshot {'bake' if Ability.BAKE in info(provider_kind).abilities else 'build'} -i INVENTORY first"
        raise InputError(f"{why}: clones made from it would not have it", hint=hint)


# -- each clone's nodes --------------------------------------------------------------------------------

def systemd_word(word: str) -> str:
    """One argv word for a unit's ExecStart=: double-quoted, with systemd's own escapes, so
    `$VAR`, `%n`, quotes and backslashes reach the program as written."""
    escaped = word.replace("\\", "\\\\").replace('"', '\\"').replace("%", "%%").replace("$", "$$")
    return f'"{escaped}"'


def node_unit(node: RunNode, digest: str) -> str:
    from ..templates import static  # here: `ccrp status` reads the nodes' service and renders no unit

    limits = []
    if node.cpu is not None:
        limits.append(f"CPUQuota={round(node.cpu * 100)}%")
    if node.memory is not None:
        limits.append(f"MemoryMax={node.memory}")  # bytes
    return static("systemd/ccrp-run.service").format(
        name=node.name, exec=" ".join([ROS_RUN, *(systemd_word(w) for w in node.command)]), restart=node.restart,
        limits="\n".join(limits), digest=digest)


def node_files(inv: Inventory, robot: Robot, software_digest: str) -> list[BundleFile]:
    """The units of robot's `run` nodes and the index of them (INDEX), whose digest per node says
    which to restart."""
    nodes = inv.software_of(robot).run
    if not nodes:
        return []
    files, index = [], {}
    for node in nodes:
        digest = hashlib.sha256(json.dumps([node.model_dump(), software_digest]).encode()).hexdigest()[:16]
        files.append(BundleFile(unit_name(node.name), node_unit(node, digest), 0o644, f"{UNIT_DIR}/{unit_name(node.name)}"))
        index[node.name] = digest
    return files + [BundleFile("workloads.json", json.dumps({"nodes": index, "software": software_digest}) + "\n",
                               0o644, INDEX)]


@dataclass(frozen=True)
class DeployInputs:
    """What `ccrp deploy` takes from the inventory, read once before anything changes: the software
    (the workspace's files and packages) with its digest, and per target robot its node units and
    index at that digest. ops/deploy.py reads the inventory only through it."""
    inventory: Inventory  # handed on whole to the install space's build (providers.build_workspace)
    software: SnapshotSoftware
    digest: str  # software.digest, hashed once (it covers the whole workspace)
    nodes: Mapping[str, list[BundleFile]]  # robot -> node_files at `digest`

    @classmethod
    def read(cls, fleet: Fleet, state: FleetState, robots: list[str]) -> DeployInputs:
        """The inventory's software read and checked (InputError), the node files of `robots`."""
        inv = fleet.inventory
        software = snapshot_software(inv, fleet.path)
        digest = software.digest
        return cls(inv, software, digest, {r: node_files(inv, fleet.robot(state, r), digest) for r in robots})


# Brings the clone's node units in line with the index just pushed ($1: the nodes to keep, then
# the nodes to restart). Names are NodeNames ([a-z][a-z0-9-]*): word splitting them is safe.
# A node that ended badly when stopped stays listed as failed: reset-failed forgets it.
APPLY_SH = r"""
keep="$1"; shift; gone=""
for f in /etc/systemd/system/ccrp-run-*.service; do
  [ -e "$f" ] || continue
  n=${f##*/ccrp-run-}; n=${n%.service}
  case " $keep " in *" $n "*) ;; *) systemctl disable --now "ccrp-run-$n.service" >/dev/null 2>&1; rm -f "$f"
                                    gone="$gone ccrp-run-$n.service";; esac
done
systemctl daemon-reload
[ -z "$gone" ] || systemctl reset-failed $gone >/dev/null 2>&1
for n in $keep; do systemctl enable "ccrp-run-$n.service" 2>/dev/null || exit 1; done
for n in "$@"; do systemctl restart "ccrp-run-$n.service" || exit 1; done
for n in $keep; do systemctl start "ccrp-run-$n.service" || exit 1; done
"""


def absent_index() -> BundleFile:
    """Probed on a clone whose robot runs no node: if it holds an index, its nodes are removed."""
    return BundleFile("workloads.json", "", 0o644, INDEX)


def apply_nodes(provider: Reaches, robot: str, files: list[BundleFile], have: dict[str, str]) -> list[str]:
    """Push the units that changed and (re)start them; stop and remove the nodes no longer
    named. Returns the nodes restarted or started anew."""
    from ..probe import same

    if not files:
        if INDEX in have:  # it ran nodes before: none now
            rc, out = provider.transport.exec(robot, ["sh", "-c", APPLY_SH + f'rm -f "{INDEX}"\n', "ccrp-nodes", ""], timeout=120)
            if rc != 0:
                raise CcrpError(f"cannot remove the nodes of robot {robot!r}'s clone: {out.strip()[-300:]}")
        return []
    changed = [f for f in files if not same(have, [f])]
    if not changed:
        return []
    index = json.loads(files[-1].content)["nodes"]
    restart = [f.name.removeprefix(UNIT_PREFIX).removesuffix(".service") for f in changed if f.dest != INDEX]
    provider.transport.push_files(robot, changed, restart=[])
    rc, out = provider.transport.exec(robot, ["sh", "-c", APPLY_SH, "ccrp-nodes", " ".join(index), *restart], timeout=120)
    if rc != 0:
        raise CcrpError(f"cannot start the nodes of robot {robot!r}'s clone: {out.strip()[-300:]}")
    return restart


# A node (re)started by `ccrp deploy`, `fleet up` or a clone's start must stay active this long,
# without an automatic restart: a node whose program is missing crash-loops, and systemd shows it
# `activating` between tries.
HEALTH_SECONDS = 3.0
HEALTH_INTERVAL = 0.5
JOURNAL_LINES = 5  # of a failing node's log, in its robot's result


def node_health(provider: Reaches, robot: str, nodes: list[str], stop: threading.Event | None = None) -> tuple[str, str] | None:
    """(unit, why) of the first of `nodes` that is not active, or is restarted by systemd, during
    HEALTH_SECONDS: one window for them all, one `systemctl show` each HEALTH_INTERVAL. None when
    all stayed up (at once when there are none). `stop` (a threading.Event): once set, the check
    raises Stopped, so an interrupted command does not wait it out."""
    units = [unit_name(n) for n in nodes]
    if not units:
        return None
    first: dict[str, int] = {}
    end = time.monotonic() + HEALTH_SECONDS
    while True:
        if stop is not None and stop.is_set():
            raise Stopped()
        _, out = provider.transport.exec(robot, ["systemctl", "show", "--property", "Id,ActiveState,SubState,NRestarts",
                                                 *units], timeout=20)
        seen = {}
        for block in out.strip().split("\n\n"):
            props = dict(line.split("=", 1) for line in block.splitlines() if "=" in line)
            if props.get("Id"):
                seen[props["Id"]] = props
        for unit in units:
            props = seen.get(unit, {})
            state = f"{props.get('ActiveState', '?')}/{props.get('SubState', '?')}"
            if props.get("ActiveState") != "active":
                return unit, f"is {state}"
            restarts = int(props.get("NRestarts", "0") or 0)
            if restarts > first.setdefault(unit, restarts):
                return unit, f"restarted {restarts - first[unit]} time(s)"
        if time.monotonic() >= end:
            return None
        time.sleep(HEALTH_INTERVAL)


class Stopped(Exception):
    """The command was interrupted (Ctrl-C) while a clone's nodes were being checked."""


def last_lines(provider: Reaches, robot: str, unit: str) -> str:
    """The last JOURNAL_LINES of unit's journal on robot's clone, in one line."""
    try:
        entries, _ = read_journal(provider, robot, [unit], JOURNAL_LINES)
    except CcrpError as exc:
        return f"(journal unreadable: {exc.message})"
    return " | ".join(e["message"] for e in entries[-JOURNAL_LINES:]) or "(no journal lines)"


def started_nodes_failing(provider: Reaches, robot: str, files: list[BundleFile], started: list[str],
                          booted: bool) -> str | None:
    """Whether the nodes `fleet up`, `clone create`, `fleet scale` or a clone's start started stay
    up (deploy's check, node_health): those apply_nodes (re)started, and every node of a clone that
    has just booted (its enabled units started with it). None when they do; else one line naming
    the robot, the node and its last journal lines."""
    nodes = list(json.loads(files[-1].content)["nodes"]) if files else []
    checked = nodes if booted else [n for n in nodes if n in started]
    failing = node_health(provider, robot, checked)
    if failing is None:
        return None
    unit, why = failing
    node = unit.removeprefix(UNIT_PREFIX).removesuffix(".service")
    return (f"robot {robot!r}'s node {node} ({unit}) {why}: it does not stay up "
            f"(ccrp logs --robot {robot} {node}); its last lines: {last_lines(provider, robot, unit)}")


class Nodes(CloneService):
    """The robot's `run` nodes: their units and index pushed, changed ones restarted, once the clone
    serves; their code is the snapshot's (or what `ccrp deploy` left on a kept clone)."""

    name = "nodes"

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        return node_files(ctx.fleet.inventory, ctx.robot, ctx.software or NO_SOFTWARE)

    def absent(self) -> list[BundleFile]:
        return [absent_index()]

    def apply(self, clone: Reaches, robot: str, files: list[BundleFile], have: dict[str, str],
              pushed_keys: bool) -> list[str]:
        return apply_nodes(clone, robot, files, have)

    def verify(self, clone: Reaches, robot: str, files: list[BundleFile], started: list[str],
               booted: bool) -> str | None:
        return started_nodes_failing(clone, robot, files, started, booted)

    def status(self, fleet: Fleet, state: FleetState, robot: Robot, health: dict | None) -> dict:
        return {} if health is None else {"nodes": health.get("nodes") or None}


# -- logs ------------------------------------------------------------------------------------------

# ccrp's own units on a clone, by the name `ccrp logs` takes (their unit is ccrp-<name>.service).
CCRP_UNITS = ("openvpn", "relay", "rosmaster", "graph", "autostop", "power", "knowledge", "api-manager", "firewall")


def log_units(inv: Inventory, robot: Robot, name: str | None) -> list[str]:
    """The units `ccrp logs` reads: every node of robot's, one node, or one of ccrp's own units."""
    nodes = [n.name for n in inv.software_of(robot).run]
    if name is None:
        if not nodes:
            raise InputError(f"robot {robot.name!r} runs no node of its own (software.run)",
                             hint=f"name one of ccrp's units instead: {', '.join(CCRP_UNITS)}")
        return [unit_name(n) for n in nodes]
    if name in nodes:
        return [unit_name(name)]
    if name in CCRP_UNITS:
        return [f"ccrp-{name}.service"]
    raise InputError(f"{shown(name)} is neither a node of robot {robot.name!r} nor a ccrp unit",
                     hint=f"nodes: {', '.join(nodes) or 'none'}; ccrp units: {', '.join(CCRP_UNITS)}")


def read_journal(provider: Reaches, robot: str, units: list[str], lines: int, since_s: int | None = None,
                 cursor: str | None = None) -> tuple[list[dict], str | None]:
    """Journal entries of `units` on robot's clone (the last `lines`, or the first `lines` after
    `cursor`), each {time, unit, message}, and the cursor to read on from. Through the provider's
    exec, so the same on every backend. The text is the clone's, exactly: a terminal gets it
    through cli/output.py, which escapes control characters.

    One answer is bounded: `lines` entries, and journalctl's JSON gives a field over 4096 bytes as
    null (no --all), so a node that logs huge lines or floods cannot fill the operator's memory."""
    argv = ["journalctl", "--no-pager", "--output", "json", "--output-fields",
            "MESSAGE,_SYSTEMD_UNIT,UNIT,_PID,SYSLOG_IDENTIFIER"]
    for name in units:
        argv += ["--unit", name]
    if cursor:
        argv += ["--after-cursor", cursor, "--lines", str(lines)]  # the first `lines` after the cursor
    else:
        argv += ["--lines", str(lines)]
        if since_s:
            argv += ["--since", f"-{since_s}s"]
    rc, out = provider.transport.exec(robot, argv, timeout=30)
    if rc != 0 and not out.lstrip().startswith("{"):
        raise CcrpError(f"cannot read the journal of robot {robot!r}'s clone: {out.strip()[-200:]}")
    entries = []
    for line in out.splitlines():
        try:
            e = json.loads(line)
        except ValueError:
            continue
        if not isinstance(e, dict):
            continue
        cursor = e.get("__CURSOR", cursor)
        message = e.get("MESSAGE")
        if isinstance(message, list):  # journald gives bytes that are not UTF-8 as a list of ints
            message = bytes(b for b in message if isinstance(b, int) and 0 <= b < 256).decode(errors="replace")
        micros = e.get("__REALTIME_TIMESTAMP")
        # The unit is journald's _SYSTEMD_UNIT (from the sender's cgroup; a field with `_` no sender
        # sets). UNIT is any sender's to write, so a node could label its lines as another unit's: it
        # counts only from systemd itself (_PID 1: the unit started, failed, is restarting).
        unit = (e.get("UNIT") if e.get("_PID") == "1" else None) or e.get("_SYSTEMD_UNIT")
        entries.append({"time": _iso(micros), "unit": unit if isinstance(unit, str) else "", "cursor": e.get("__CURSOR"),
                        "ident": e.get("SYSLOG_IDENTIFIER") or "", "message": message if isinstance(message, str) else ""})
    return entries, cursor


def _iso(micros: Any) -> str:  # journald's __REALTIME_TIMESTAMP, whatever the clone sent
    import datetime as dt

    try:
        # Exact to the microsecond (a float of seconds is not), since `ccrp logs` merges clones by it.
        epoch = dt.datetime(1970, 1, 1, tzinfo=dt.timezone.utc)
        return (epoch + dt.timedelta(microseconds=int(micros))).isoformat(timespec="microseconds")
    except (TypeError, ValueError, OverflowError):
        return ""
