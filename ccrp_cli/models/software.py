"""The robot's own software on its clone (docs/workloads.md): the inventory's `software:`, given
fleet-wide, per robot type (`types.<type>.software`) and per robot (`robots[].software`).

Merged fleet -> type -> robot: `apt` and `pip` lists add up, a `run` entry replaces the entry of
the same name from the level before, `env` adds up name by name (a later level's value wins),
`workspace` is the last one given. Every value that reaches
a rendered file (a systemd unit, a Dockerfile, user-data) is typed here first: a Debian package
name, a pip requirement, a unit name, an argv without control characters.
"""

from __future__ import annotations

import re
from pathlib import PurePosixPath
from typing import Annotated, Literal

from pydantic import AfterValidator, BeforeValidator, Field, StringConstraints, field_validator, model_validator

from ..errors import shown
from .distro import RobotRos
from .names import Topic
from .strict import Strict
from .values import Size

# Debian policy 5.6.1: lower case letters, digits, + - . ; at least two characters, a letter or digit first.
DebPackage = Annotated[str, StringConstraints(pattern=r"^[a-z0-9][a-z0-9+.-]{1,99}$")]
# A node's name becomes the unit ccrp-run-<name>.service and a journal's unit filter.
NodeName = Annotated[str, StringConstraints(pattern=r"^[a-z][a-z0-9-]{0,39}$")]

# Words a shell gives meaning to: an argv holding one of them alone was written as a shell line.
SHELL_WORDS = {"|", "||", "&", "&&", ";", ";;", ">", ">>", "<", "<<", "2>", "2>&1", "$(", "`", "(", ")"}
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_REQUIREMENT = re.compile(r"[A-Za-z0-9._\-\[\],<>=!~*+]+")


def _requirement(text: object) -> object:
    """A pip requirement as pip reads it (name, extras, version specifiers, markers), nothing more:
    no URL, path or option (`-e`, `--index-url`), which would fetch from elsewhere."""
    if not isinstance(text, str):
        return text
    from packaging.requirements import InvalidRequirement, Requirement

    if text.startswith("-") or _CONTROL.search(text) or len(text) > 200:
        raise ValueError(f"{shown(text)} is not a pip requirement (name and version specifiers only)")
    try:
        req = Requirement(text)
    except InvalidRequirement:
        raise ValueError(f"{shown(text)} is not a pip requirement (e.g. numpy>=1.24)") from None
    if req.url:
        raise ValueError(f"{shown(text)}: a requirement from a URL is not taken; name the package on the index")
    if req.marker:
        raise ValueError(f"{shown(text)}: environment markers are not taken (every clone runs the same Python)")
    if not _REQUIREMENT.fullmatch(str(req)):  # it becomes one word of a build command
        raise ValueError(f"{shown(text)} is not a pip requirement (name, extras and version specifiers only)")
    return str(req)


PipRequirement = Annotated[str, BeforeValidator(_requirement)]


def _inside(text: str, label: str, kind: str) -> str:
    """A path on the operator's side, relative to the inventory's directory and never leaving it."""
    path = PurePosixPath(text)
    if not text or _CONTROL.search(text) or len(text) > 200:
        raise ValueError(f"{shown(text)} is not a {label} {kind}")
    if path.is_absolute() or ".." in path.parts:
        raise ValueError(f"{label} {shown(text)}: give a {kind} inside the inventory's, relative to it")
    return text


def _workspace(text: str) -> str:
    return _inside(text, "workspace", "directory")


def _secret_file(text: str) -> str:
    return _inside(text, "secret", "file")


# What ccrp itself sets in a node's environment (the unit, ros.env, ros-run, systemd): a node's
# `env` giving one would be overridden or undone without a word (EnvironmentFile= wins over
# Environment=, ros-run unsets the search paths), or break the node's ROS wiring, so it is refused.
RESERVED_ENV = {
    "PATH", "HOME", "USER", "LOGNAME", "SHELL", "PWD", "TERM", "LANG", "CREDENTIALS_DIRECTORY", "INVOCATION_ID",
    "JOURNAL_STREAM", "NOTIFY_SOCKET", "LISTEN_FDS", "LISTEN_PID", "LISTEN_FDNAMES", "RUNTIME_DIRECTORY",
    "ROS_DISTRO", "ROS_MASTER_URI", "ROS_MASTER_PORT", "ROS_HOSTNAME", "ROS_IP", "ROS_DOMAIN_ID",
    "ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY", "RMW_IMPLEMENTATION",
    "FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE",
    "PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PYTHONUSERBASE", "PYTHONNOUSERSITE", "LD_LIBRARY_PATH",
    "LD_PRELOAD", "AMENT_PREFIX_PATH", "CMAKE_PREFIX_PATH", "COLCON_PREFIX_PATH", "ROS_PACKAGE_PATH",
    "PKG_CONFIG_PATH",
}
_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,127}")
# A credential's name is a file name in $CREDENTIALS_DIRECTORY (and on the clone).
SecretName = Annotated[str, StringConstraints(pattern=r"^[A-Za-z_][A-Za-z0-9_.-]{0,63}$")]


def _env_name(name: str) -> str:
    if not _ENV_NAME.fullmatch(name):
        raise ValueError(f"env name {shown(name)} is not an environment variable name (letters, digits and _, "
                         "not a digit first)")
    if name in RESERVED_ENV or name.startswith(("CCRP_", "SYSTEMD_")):
        raise ValueError(f"env name {shown(name)} is ccrp's or systemd's to set on the clone; choose another name")
    return name


def _env_value(value: object) -> object:
    # YAML gives `PORT: 8080` as a number: taken as its text. `true`/`yes`/`on` would come out
    # as True, whose text the user did not write: quote it.
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ValueError(f"env value {shown(value)} is not text: quote it (\"true\", \"1\")")
    text = str(value)
    if _CONTROL.search(text) or len(text) > 4096:
        raise ValueError(f"env value {shown(text)} is not one line of at most 4096 characters without control characters")
    return text


EnvName = Annotated[str, AfterValidator(_env_name)]
EnvValue = Annotated[str, BeforeValidator(_env_value)]
Env = Annotated[dict[EnvName, EnvValue], Field(max_length=100)]


def _argv(value: object) -> object:
    if isinstance(value, str):
        raise ValueError(f"command {shown(value)}: give the command as a list of words, e.g. "
                         "[python3, -m, my_pkg.node]; it runs without a shell")
    return value


def _words(argv: list[str]) -> list[str]:
    for word in argv:
        if _CONTROL.search(word):
            raise ValueError(f"command word {shown(word)} holds a control character")
        if word.strip() in SHELL_WORDS:
            raise ValueError(f"command {shown(' '.join(argv))}: {word!r} means something to a shell only, and the "
                             "command runs without one; run a script of your workspace instead")
    return argv


Argv = Annotated[
    list[Annotated[str, StringConstraints(min_length=1, max_length=1000)]],
    BeforeValidator(_argv), AfterValidator(_words), Field(min_length=1, max_length=64),
]


class Ready(Strict):
    """When a node counts as ready (docs/workloads.md, Readiness): a message on `topic`, or
    `command` exiting 0 (as the node's user, in its environment), within `within` seconds of its
    start. Without it a node is ready when it stays up for the first 3 s."""

    topic: Topic | None = None
    command: Argv | None = None
    within: Annotated[int, Field(strict=True, ge=1, le=900)] = 30

    @model_validator(mode="after")
    def _one(self) -> Ready:
        if (self.topic is None) == (self.command is None):
            raise ValueError("ready: give either topic (a message must arrive on it) or command (it must exit 0)")
        return self


class RunNode(Strict):
    """A node kept running on the clone: the unit ccrp-run-<name>, as the `ros` user, in the
    clone's ROS environment (and the workspace's, when there is one)."""

    name: NodeName
    command: Argv
    # systemd's Restart=: on-failure (the default) restarts after a crash or a non-zero exit.
    restart: Literal["on-failure", "always", "no"] = "on-failure"
    # CPU cores the node may use (CPUQuota), e.g. 0.5 or 2.
    cpu: Annotated[float, Field(strict=True, gt=0, le=256)] | None = None
    # Memory it may use (MemoryMax), a size as elsewhere in the inventory: 512MiB, 2GB.
    memory: Size | None = None
    # Environment variables of this node, over its software level's `env` (not for secrets: they
    # are in its unit, which anyone on the clone can read).
    env: Env = {}
    # Credentials: NAME -> a file on the operator's side, relative to the inventory. The node reads
    # it as $CREDENTIALS_DIRECTORY/NAME (systemd's LoadCredential=), and nowhere else has it.
    secrets: Annotated[dict[SecretName, Annotated[str, AfterValidator(_secret_file)]], Field(max_length=16)] = {}
    # Readiness beyond "stays up": checked by fleet up, clone create, fleet scale and deploy (which
    # rolls the clone back when it fails).
    ready: Ready | None = None

    @field_validator("cpu", mode="before")
    @classmethod
    def _number(cls, value: object) -> object:
        if isinstance(value, bool) or not isinstance(value, (int, float)) and value is not None:
            raise ValueError(f"{shown(str(value))} is not a number of CPU cores (e.g. 0.5 or 2)")
        return float(value) if value is not None else None


class Software(Strict):
    # Debian packages (ROS 1 fleets: Debian's ROS packages; any fleet: libraries, tools).
    apt: list[DebPackage] = Field(default=[], max_length=200)
    # Python requirements, installed for the clone's ROS python.
    pip: list[PipRequirement] = Field(default=[], max_length=200)
    # A catkin (ROS 1) or colcon/ament_python (ROS 2) workspace, relative to the inventory.
    workspace: Annotated[str, AfterValidator(_workspace)] | None = None
    # Environment variables of every node of this level and below (a node's own `env` wins).
    env: Env = {}
    run: list[RunNode] = Field(default=[], max_length=50)

    @field_validator("run")
    @classmethod
    def _unique_run(cls, nodes: list[RunNode]) -> list[RunNode]:
        names = [n.name for n in nodes]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"run: {', '.join(dup)} given twice")
        return nodes


class TypeSettings(Strict):
    """What every robot of a type shares (`types.<type>:`)."""

    software: Software | None = None
    ros: RobotRos | None = None  # the ROS its robots run, when said: the fleet's (models/distro.py)


def merge(*levels: Software | None) -> Software:
    """fleet -> type -> robot: lists add (each package once, first place kept), a `run` entry
    replaces the one of the same name, `env` adds name by name (the later value wins), `workspace`
    is the last one given."""
    apt: list[str] = []
    pip: list[str] = []
    env: dict[str, str] = {}
    run: dict[str, RunNode] = {}
    workspace = None
    for level in levels:
        if level is None:
            continue
        apt += [p for p in level.apt if p not in apt]
        pip += [p for p in level.pip if p not in pip]
        env.update(level.env)
        run.update({n.name: n for n in level.run})
        workspace = level.workspace or workspace
    return Software(apt=apt, pip=pip, workspace=workspace, env=env, run=list(run.values()))
