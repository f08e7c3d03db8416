"""The robot's own software on its clone (docs/workloads.md): the workspace's packages and what
they depend on, the digest a snapshot carries, each clone's node units, their state and logs.

The snapshot holds the software (packages, the built workspace); `fleet up` gives each clone the
units of its robot's `run` nodes and starts them. Every name that reaches a unit or a command line
is a NodeName ([a-z][a-z0-9-]*); a node's argv is escaped for systemd, never given to a shell.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import CcrpError, InputError, shown
from ..models.inventory import Inventory, Robot
from ..models.layout import SECRETS_DIR
from ..models.software import Ready, RunNode, Software
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
# A node's secrets, CREDENTIALS/<node>/<NAME> (root, 0600), handed to it by systemd's LoadCredential=.
# In the directory of the clone's keys, never on its root disk: a tmpfs on the clouds, the clone's
# own volume on Docker, so no snapshot captures them (models/layout.py SECRETS_DIR).
CREDENTIALS = f"{SECRETS_DIR}/nodes"
# Required by the node units with secrets, an instance per node: its credentials directory made a
# mount of its own in the clone's namespace before the node starts, which systemd then fills in place
# and hands to the node. A new one systemd 252 fills in a namespace of its own and moves to
# /run/credentials/<unit>, which reaches the node only where /run propagates mounts: on a VM, not in
# a Docker clone, whose /run is a private tmpfs (making it shared made Docker's archive calls on the
# container hang). From inside the node's own namespace (ProtectSystem=, PrivateTmp=) no ExecStartPre
# could mount it: hence a unit of its own, run again at each start of the node (templates/systemd/).
CREDENTIALS_UNIT = "ccrp-credentials@.service"
MAX_SECRET_BYTES = 64 << 10
MAX_CLONE_SECRET_BYTES = 1 << 20  # that tmpfs holds 4 MB, the VPN's keys too
ROS_RUN = "/usr/local/lib/ccrp/ros-run"
NO_SOFTWARE = "none"  # the digest of a snapshot (or inventory) without software of the user's

# Directories of a workspace that are build output, not source (catkin, colcon) or tool state.
SKIP_DIRS = {"build", "devel", "install", "log", "logs", "__pycache__", ".git", ".hg", ".svn"}
MAX_WORKSPACE_BYTES = 64 << 20  # goes into a build context (Docker) or over SSH (clouds)
SAFE_PATH = re.compile(r"[A-Za-z0-9._+/-]{1,200}")
# A ROS 2 workspace: Python packages, and interface packages built with CMake from the wheels'
# ament_cmake and rosidl generators (no rclcpp*: PyPI has no wheel of them).
ROS2_BUILD_TYPES = ("ament_python", "ament_cmake")
ROS_PACKAGE_NAME = re.compile(r"[a-z][a-z0-9_]{0,99}")
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
    uses: tuple[str, ...] = ()  # the workspace's own packages it depends on


def package_dir(pkg: Package) -> str:
    """The package's directory, relative to the workspace: a word of the snapshot's build."""
    return pkg.path.rsplit("/", 1)[0] if "/" in pkg.path else "."


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
    return [Package(name, bt, tuple(dict.fromkeys(k for k in keys if k and k not in own)), rel,
                    tuple(dict.fromkeys(k for k in keys if k in own and k != name)))
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
        if is_ros2(distro) and pkg.build_type not in ROS2_BUILD_TYPES:
            raise InputError(f"package {shown(pkg.name)} ({pkg.path}) is {shown(pkg.build_type)}: a ROS 2 workspace here builds "
                             "ament_python packages and ament_cmake interface packages (.msg, .srv, .action)")
        if not is_ros2(distro) and pkg.build_type != "catkin":
            raise InputError(f"package {shown(pkg.name)} ({pkg.path}) is {shown(pkg.build_type)}: a ROS 1 workspace builds catkin packages")
        if pkg.build_type == "ament_cmake" and not ROS_PACKAGE_NAME.fullmatch(pkg.name):
            raise InputError(f"package {shown(pkg.name)} ({pkg.path}): an interface package's name is lower-case letters, "
                             "digits and _ (REP 144), starting with a letter")
        for key in pkg.depends:
            if is_ros2(distro) and key.startswith("rclcpp"):
                raise InputError(f"package {shown(pkg.name)} depends on {key}: the ROS 2 wheels have no rclcpp (C++); "
                                 "write the node in Python (rclpy), and keep ament_cmake packages to interfaces")
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
    platform: str = "debian-bookworm"  # the recipe's platform the clones run (Inventory.clone_platform)
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
        """How the workspace is built: `catkin` (ROS 1), `ament` (ROS 2: its interface packages
        with CMake, then its Python packages with pip), None without a workspace."""
        if not self.packages:
            return None
        return "catkin" if self.packages[0].build_type == "catkin" else "ament"

    @property
    def interfaces(self) -> list[Package]:
        """The ament_cmake (interface) packages, each after those of the workspace it depends on."""
        left = {p.name: p for p in self.packages if p.build_type == "ament_cmake"}
        out: list[Package] = []
        while left:
            ready = [p for p in left.values() if not set(p.uses) & set(left)]
            if not ready:
                raise InputError(f"the workspace's interface packages depend on each other in a cycle: {', '.join(sorted(left))}")
            for p in sorted(ready, key=lambda p: p.name):
                out.append(left.pop(p.name))
        return out

    @property
    def interface_words(self) -> list[str]:
        """The interface packages as the build takes them: NAME=DIR, in build order."""
        return [f"{p.name}={package_dir(p)}" for p in self.interfaces]

    @property
    def python_dirs(self) -> list[str]:
        """The directories of the ament_python packages, which pip installs."""
        return sorted({package_dir(p) for p in self.packages if p.build_type == "ament_python"})

    @property
    def build_tools(self) -> Resolved:
        """What building the workspace needs beside its packages' own keys, from the recipe: catkin's
        compiler and tools, or for interface packages CMake, the compiler and the wheels of ament_cmake
        and the rosidl generators (none on a platform whose ROS is installed: its own has them)."""
        from ..recipes import platform, recipe

        tools = recipe(self.distro).build_tools
        if self.build_type == "catkin":
            return Resolved(apt=list(tools.apt))
        if not self.interfaces:
            return Resolved()
        return Resolved(apt=list(tools.apt), pip=[] if platform(self.distro, self.platform).ros_installed else list(tools.pip))

    @property
    def pip_install(self) -> list[str]:
        """What pip installs: the requirements, and `wheel` for ament_python packages (it builds
        them in the venv, whose setuptools has no bdist_wheel of its own)."""
        return self.pip + (["wheel"] if self.python_dirs else [])

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
    out = SnapshotSoftware(spec=spec, distro=inv.ros.distro, platform=inv.clone_platform)
    root = workspace_dir(inv_path, spec)
    if root is not None:
        out.workspace = workspace_files(root)
        out.packages = scan_packages(root, out.workspace)
        out.resolved = resolve(inv.ros.distro, out.packages)
        out.interfaces  # noqa: B018 - a cycle among them is refused here, before anything is built
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


def systemd_env(name: str, value: str) -> str:
    """One Environment= assignment, double-quoted for systemd: it expands specifiers (`%`) and C
    escapes there, never `$` (nor a shell: there is none)."""
    escaped = value.replace("\\", "\\\\").replace('"', '\\"').replace("%", "%%")
    return f'Environment="{name}={escaped}"'


def credential_path(node: str, name: str) -> str:
    return f"{CREDENTIALS}/{node}/{name}"


def node_unit(node: RunNode, digest: str, env: Mapping[str, str] | None = None) -> str:
    """The unit of `node`; `env`: its environment, its software level's with its own over it."""
    from ..templates import static  # here: `ccrp status` reads the nodes' service and renders no unit

    limits = []
    if node.cpu is not None:
        limits.append(f"CPUQuota={round(node.cpu * 100)}%")
    if node.memory is not None:
        limits.append(f"MemoryMax={node.memory}")  # bytes
    # Names and paths are the models' (letters, digits, _ . -): nothing to quote.
    settings = [systemd_env(k, v) for k, v in (env if env is not None else node.env).items()]
    settings += [f"LoadCredential={name}:{credential_path(node.name, name)}" for name in node.secrets]
    mount = CREDENTIALS_UNIT.replace("@", "@%n")
    requires = f"Requires={mount}\nAfter={mount}" if node.secrets else ""
    return static("systemd/ccrp-run.service").format(
        name=node.name, requires=requires, exec=" ".join([ROS_RUN, *(systemd_word(w) for w in node.command)]), restart=node.restart,
        settings="\n".join(settings), limits="\n".join(limits), digest=digest)


def secret_files(inv_path: Path | None, robot: str, nodes: list[RunNode]) -> list[BundleFile]:
    """The secrets of `nodes` read from the operator's side (files relative to the inventory), as
    the root-only files their units load. Refused in one line (InputError) when one is missing,
    unreadable, not text, too big, or leads out of the inventory's directory; a value is never
    shown."""
    base = (inv_path.parent if inv_path is not None else Path.cwd()).resolve()
    files, total = [], 0
    for node in nodes:
        for name, rel in node.secrets.items():
            where = f"robot {robot!r}'s node {node.name} secret {name} ({shown(rel)})"
            path = (base / rel).resolve()
            if not path.is_relative_to(base):  # a link to elsewhere (`token -> ~/.ssh/id_ed25519`)
                raise InputError(f"{where} leads out of the inventory's directory",
                                 hint="keep the secret's file itself in the inventory's directory")
            try:
                data = path.read_bytes() if path.is_file() else None
            except OSError as exc:
                raise InputError(f"{where} is not readable: {exc.strerror}") from None
            if data is None:
                raise InputError(f"{where}: no such file", hint="give a file relative to the inventory's directory")
            total += len(data)
            if len(data) > MAX_SECRET_BYTES or total > MAX_CLONE_SECRET_BYTES:
                raise InputError(f"{where}: a secret holds at most {MAX_SECRET_BYTES >> 10} KiB, a clone's "
                                 f"{MAX_CLONE_SECRET_BYTES >> 20} MiB in all")
            try:
                text = data.decode()
            except UnicodeDecodeError:
                raise InputError(f"{where} is not text (UTF-8)", hint="give a binary secret base64-encoded") from None
            files.append(BundleFile(f"{node.name}/{name}", text, 0o600, credential_path(node.name, name)))
    return files


def check_secrets(fleet: Fleet, state: FleetState, robots: list[str]) -> None:
    """Every secret the nodes of `robots` name is there and readable (InputError): said before
    anything changes, not on the one clone that gets it. A robot `fleet scale` is about to add (not
    in state yet) has the template's software."""
    known = {r.name: r for r in fleet.members(state)}
    template = fleet.inventory.template
    for name in robots:
        robot = known.get(name) or (Robot(name=name, type=template.type, software=template.software) if template else None)
        if robot is not None:
            secret_files(fleet.path, name, fleet.inventory.software_of(robot).run)


def node_files(inv: Inventory, robot: Robot, software_digest: str, inv_path: Path | None = None) -> list[BundleFile]:
    """The units of robot's `run` nodes, their secrets (read from the operator's side, relative to
    `inv_path`'s directory) and the index of the nodes (INDEX, last), whose digest per node says
    which to restart. A secret's content is not in the digest (the index is anyone's to read on the
    clone): a changed one shows as its file's digest, which the clone's probe compares."""
    software = inv.software_of(robot)
    if not software.run:
        return []
    units, index = [], {}
    for node in software.run:
        env = {**software.env, **node.env}
        # Readiness is ccrp's check, not the unit's: changing it restarts nothing.
        digest = hashlib.sha256(json.dumps([node.model_dump(exclude={"ready"}), env, software_digest]).encode()).hexdigest()[:16]
        units.append(BundleFile(unit_name(node.name), node_unit(node, digest, env), 0o644,
                                f"{UNIT_DIR}/{unit_name(node.name)}"))
        index[node.name] = digest
    content = {"nodes": index, "software": software_digest}
    if ready := {n.name: n.ready.model_dump(exclude_none=True) for n in software.run if n.ready}:
        content["ready"] = ready  # what fleet up and deploy check (readiness); absent when no node has one
    secrets = secret_files(inv_path, robot.name, software.run)
    if secrets:
        from ..templates import static

        units.append(BundleFile(CREDENTIALS_UNIT, static(f"systemd/{CREDENTIALS_UNIT}"), 0o644, f"{UNIT_DIR}/{CREDENTIALS_UNIT}"))
    return [*units, *secrets, BundleFile("workloads.json", json.dumps(content) + "\n", 0o644, INDEX)]


def is_secret(f: BundleFile) -> bool:
    return bool(f.dest and f.dest.startswith(f"{CREDENTIALS}/"))


def node_of(f: BundleFile) -> str:
    """The node a unit or secret file of node_files is for."""
    return f.name.split("/")[0] if is_secret(f) else f.name.removeprefix(UNIT_PREFIX).removesuffix(".service")


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
        return cls(inv, software, digest, {r: node_files(inv, fleet.robot(state, r), digest, fleet.path) for r in robots})


# Brings the clone's node units in line with the index just pushed ($1: the nodes to keep, $2 the
# secrets to keep as <node>/<NAME>, then the nodes to restart). Names are NodeNames
# ([a-z][a-z0-9-]*) and credential names ([A-Za-z_][A-Za-z0-9_.-]*): word splitting them is safe.
# A node that ended badly when stopped stays listed as failed: reset-failed forgets it. A secret
# no longer named is deleted, with its node's directory once empty.
APPLY_SH = r"""
keep="$1"; creds="$2"; shift 2; gone=""
C=""" + CREDENTIALS + r"""
for f in "$C"/*/*; do
  [ -e "$f" ] || continue
  case " $creds " in *" ${f#"$C"/} "*) ;; *) rm -f "$f";; esac
done
for d in "$C"/*; do [ -d "$d" ] && rmdir "$d" 2>/dev/null; done
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
            rc, out = provider.transport.exec(robot, ["sh", "-c", APPLY_SH + f'rm -f "{INDEX}"\n', "ccrp-nodes", "", ""],
                                              timeout=120)
            if rc != 0:
                raise CcrpError(f"cannot remove the nodes of robot {robot!r}'s clone: {out.strip()[-300:]}")
        return []
    changed = [f for f in files if not same(have, [f])]
    if not changed:
        return []
    index = json.loads(files[-1].content)["nodes"]
    restart = list(dict.fromkeys(node_of(f) for f in changed if f.dest != INDEX and f.name != CREDENTIALS_UNIT))
    secrets = [f for f in files if is_secret(f)]
    if any(is_secret(f) for f in changed):  # root's (exec runs as root), 0700; the tmpfs is empty after a reboot
        dirs = [CREDENTIALS, *dict.fromkeys(f"{CREDENTIALS}/{node_of(f)}" for f in secrets)]
        rc, out = provider.transport.exec(robot, ["install", "-d", "-m", "0700", *dirs],
                                          timeout=30)
        if rc != 0:
            raise CcrpError(f"cannot prepare {CREDENTIALS} on robot {robot!r}'s clone: {out.strip()[-300:]}")
    provider.transport.push_files(robot, changed, restart=[])
    rc, out = provider.transport.exec(robot, ["sh", "-c", APPLY_SH, "ccrp-nodes", " ".join(index),
                                              " ".join(f.name for f in secrets), *restart], timeout=120)
    if rc != 0:
        raise CcrpError(f"cannot start the nodes of robot {robot!r}'s clone: {out.strip()[-300:]}")
    return restart


# A node (re)started by `ccrp deploy`, `fleet up` or a clone's start must stay active this long,
# without an automatic restart: a node whose program is missing crash-loops, and systemd shows it
# `activating` between tries.
HEALTH_SECONDS = 3.0
HEALTH_INTERVAL = 0.5
JOURNAL_LINES = 5  # of a failing node's log, in its robot's result


def ready_specs(files: list[BundleFile]) -> dict[str, Ready]:
    """The readiness of the nodes a clone's index names (node_files: the index is the last file)."""
    if not files:
        return {}
    ready = json.loads(files[-1].content).get("ready") or {}
    return {name: Ready.model_validate(spec) for name, spec in ready.items()}


def node_health(provider: Reaches, robot: str, nodes: list[str], stop: threading.Event | None = None,
                ready: Mapping[str, Ready] | None = None) -> tuple[str, str] | None:
    """(unit, why) of the first of `nodes` that is not active, or is restarted by systemd, during
    HEALTH_SECONDS: one window for them all, one `systemctl show` each HEALTH_INTERVAL; then of the
    first of them with a `ready` check (theirs in `ready`) that does not pass within its time from
    the start of this check. None when all stayed up and are ready (at once when there are none).
    `stop` (a threading.Event): once set, the check raises Stopped, so an interrupted command does
    not wait it out."""
    units = [unit_name(n) for n in nodes]
    if not units:
        return None
    first: dict[str, int] = {}
    start = time.monotonic()
    end = start + HEALTH_SECONDS
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
            break
        time.sleep(HEALTH_INTERVAL)
    for node in nodes:  # one after the other: each one's time runs from `start`, as they all started then
        if ready and node in ready and (why := not_ready(provider, robot, ready[node], start, stop)):
            return unit_name(node), why
    return None


# A `ready` check runs as the node's user, in the clone's ROS environment and the workspace's, as the
# node does (its unit's EnvironmentFile and ros-run). A constant script: the command comes as its arguments.
AS_NODE = ["runuser", "-u", "ros", "--", "/bin/sh", "-c",
           'set -a; . /etc/ccrp/ros.env; set +a; HOME=/var/lib/ros CCRP_WORKSPACE=1 exec "$0" "$@"', ROS_RUN]
READY_TRY_MAX = 15.0  # seconds one try of a check may take (one topic echo, one command)
READY_INTERVAL = 1.0  # between two tries of a command
NOT_READY = "was not ready within"


def ready_now(provider: Reaches, robot: str, spec: Ready) -> str | None:
    """One try of `spec` now (`ccrp status --ready`), waiting at most READY_TRY_MAX seconds (or its
    `within`) for a message or for the command: None when it passes, else why not."""
    return not_ready(provider, robot, spec.model_copy(update={"within": min(spec.within, int(READY_TRY_MAX))}),
                     time.monotonic(), once=True)


def not_ready(provider: Reaches, robot: str, spec: Ready, since: float, stop: threading.Event | None = None,
              once: bool = False) -> str | None:
    """None once `spec` passes on robot's clone (a message on its topic, its command exiting 0),
    tried again until `spec.within` seconds after `since` (a time.monotonic()), or tried once
    (`once`); else why not."""
    deadline = since + spec.within
    while True:
        if stop is not None and stop.is_set():
            raise Stopped()
        wait = max(1, math.ceil(min(deadline - time.monotonic(), READY_TRY_MAX)))
        if spec.topic is not None:
            # Heard as another node of the clone would hear it: the node's user, its environment and
            # workspace (its message types). As root, Fast DDS's shared memory between two users
            # dropped every message of a node. echo waits for the message itself.
            argv = ["timeout", str(wait + 5), *AS_NODE, "ccrp-topic", "echo", spec.topic, "-n", "1", "-t", str(wait)]
        else:
            assert spec.command is not None
            argv = ["timeout", str(wait), *AS_NODE, *spec.command]
        rc, out = provider.transport.exec(robot, argv, timeout=wait + 30)
        if rc == 0:
            return None
        if once or time.monotonic() >= deadline:
            if spec.topic is not None:
                return f"{NOT_READY} {spec.within} s: no message on {spec.topic}"
            return (f"{NOT_READY} {spec.within} s: its ready command {shown(' '.join(spec.command or []))} "
                    f"exited {rc}: {shown(out.strip()[-200:]) or '(no output)'}")
        if spec.command is not None:
            time.sleep(READY_INTERVAL)


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
    failing = node_health(provider, robot, checked, ready=ready_specs(files))
    if failing is None:
        return None
    unit, why = failing
    node = unit.removeprefix(UNIT_PREFIX).removesuffix(".service")
    verdict = "it is not ready" if why.startswith(NOT_READY) else "it does not stay up"
    return (f"robot {robot!r}'s node {node} ({unit}) {why}: {verdict} "
            f"(ccrp logs --robot {robot} {node}); its last lines: {last_lines(provider, robot, unit)}")


class Nodes(CloneService):
    """The robot's `run` nodes: their units and index pushed, changed ones restarted, once the clone
    serves; their code is the snapshot's (or what `ccrp deploy` left on a kept clone)."""

    name = "nodes"

    def check(self, fleet: Fleet, robot: Robot) -> None:
        secret_files(fleet.path, robot.name, fleet.inventory.software_of(robot).run)  # each one there and readable

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        return node_files(ctx.fleet.inventory, ctx.robot, ctx.software or NO_SOFTWARE, ctx.fleet.path)

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
