"""The inventory: a fleet's desired shape, loaded strictly from YAML."""

from __future__ import annotations

import ipaddress
from typing import Annotated, Literal, Union

from pydantic import Field, field_validator, model_validator

from ..errors import shown
from .distro import Distro, RobotRos
from .names import Name, Topic
from .software import Software, TypeSettings, merge
from .strict import ProviderSettings, Strict
from .values import CloudName, Duration, Port, Size, StrictInt

RobotType = Literal["nao", "turtlebot", "generic"]


class Autostop(Strict):
    """A clone whose robot has not been connected for `idle` powers itself off (stopped, not
    deleted); `ccrp clone start` or `fleet up` starts it again. `idle: never` turns it off."""

    idle: Duration

    @field_validator("idle")
    @classmethod
    def _in_range(cls, idle: int) -> int:
        if idle and not 30 <= idle <= 30 * 86400:
            raise ValueError("idle must be between 30s and 30d, or never")
        return idle


# A backend of the API manager: a built-in one (opencv, face-recognition, google-vision) or the
# name of a plugin's entry point in the `ccrp.api_backends` group, installed on the clone.
BACKEND_PATTERN = r"^[a-z][a-z0-9_.-]{0,39}$"
BUILTIN_BACKENDS = ("opencv", "face-recognition", "google-vision")
# A plugin's options: flat scalars only (they are pushed as JSON and passed to the plugin as is).
OptionValue = Union[Annotated[str, Field(max_length=500)], bool, StrictInt, float]


class GoogleVision(Strict):
    """The `google-vision` backend: the official google-cloud-vision client (REST transport)."""

    # host[:port], or http(s)://host[:port] (tests point it at a local endpoint).
    endpoint: Annotated[str, Field(pattern=r"^(https?://)?[A-Za-z0-9.-]{1,253}(:[0-9]{1,5})?$")] = "vision.googleapis.com"
    # A service-account key file on the operator's machine. `fleet up` pushes it to the clone's
    # secrets (never user-data); without it the client finds no credentials and every call fails.
    credentials: Annotated[str, Field(min_length=1, max_length=4096)] | None = None
    # Per call, seconds; then the call counts as an error and is retried with backoff.
    timeout: Annotated[float, Field(strict=True, gt=0, le=60)] = 5.0


class ApiManager(Strict):
    """The clone's API manager (docs/services.md): subscribes to `input` (sensor_msgs/Image), at most
    `rate` images a second are sent to `backend`, matches under `min_confidence` are dropped and the
    best one is published on `output` as JSON in a std_msgs/String."""

    enabled: bool = True
    input: Topic = "/camera/image_raw"
    output: Topic = "/api_manager/result"
    backend: Annotated[str, Field(pattern=BACKEND_PATTERN)] = "opencv"
    rate: Annotated[float, Field(gt=0, le=30)] = 1.0  # Hz
    min_confidence: Annotated[float, Field(ge=0, le=1)] = 0.5
    google_vision: GoogleVision = GoogleVision()
    options: dict[Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]{0,39}$")], OptionValue] = {}

    @field_validator("rate", "min_confidence", mode="before")
    @classmethod
    def _number(cls, value: object) -> object:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{shown(value)} is not a number")
        return value

    @model_validator(mode="after")
    def _loop_free(self) -> "ApiManager":
        if self.input == self.output:
            raise ValueError(f"api_manager input and output are the same topic {self.input}")
        return self


# A dataset's name: a directory on every clone that shares it and a Zenoh key chunk.
DATASET_PATTERN = r"^[a-z][a-z0-9_-]{0,39}$"


class Quota(Strict):
    """What one dataset may hold on each clone that shares it: live items, and their bytes. A
    partner's item past it is refused by the agent (and reported); `knowledge add` refuses in one
    line. No item is bigger than `bytes` (nor than 1 GiB, what an agent takes from a partner)."""

    items: Annotated[int, Field(strict=True, ge=1, le=1_000_000)] = 10_000
    bytes: Size = 1 << 30

    @field_validator("bytes")
    @classmethod
    def _bytes_range(cls, size: int) -> int:
        if not 1 << 10 <= size <= 1 << 40:
            raise ValueError("a dataset's quota of bytes must be between 1KiB and 1TiB")
        return size


class Dataset(Strict):
    # The robots whose clones share the dataset: named robots of the inventory, or `all` (every
    # robot of the fleet, template robots that `fleet scale` adds too).
    robots: Literal["all"] | Annotated[list[Name], Field(min_length=1, max_length=1000)]
    quota: Quota = Quota()


class Knowledge(Strict):
    """Datasets kept the same on the clones that share them (docs/services.md, Knowledge sync):
    items sent to the partners when added, and every `reconcile` a pull of their indexes."""

    datasets: dict[Annotated[str, Field(pattern=DATASET_PATTERN)], Dataset] = {}
    reconcile: Duration = 300
    # The knowledge agents' own Zenoh listener on the common network (the relay has relay_port).
    port: Port = 7448

    @field_validator("reconcile")
    @classmethod
    def _reconcile_range(cls, seconds: int) -> int:
        if not 5 <= seconds <= 86400:
            raise ValueError("reconcile must be between 5s and 1d")
        return seconds


class Services(Strict):
    """Platform services on the clone (docs/services.md)."""

    api_manager: ApiManager | None = None
    # Fleet-wide only: a dataset names the robots that share it.
    knowledge: Knowledge | None = None


class Robot(Strict):
    name: Name
    type: RobotType = "generic"
    # Topics this robot's clone shares with the fleet (absolute ROS names).
    exports: list[Topic] = []
    # Topics taken from other robots' clones, by source robot; they appear as /<source><topic>.
    imports: dict[Name, list[Topic]] = {}
    # Per-robot provider overrides (instance size, zone).
    instance_type: CloudName | None = None
    zone: CloudName | None = None
    # Replaces the fleet's `autostop` for this robot's clone.
    autostop: Autostop | None = None
    # Each service given here replaces the fleet's setting of it for this robot's clone.
    services: Services = Services()
    # Added to the fleet's and its type's software (docs/workloads.md).
    software: Software | None = None
    # The ROS the robot itself runs, when said: the fleet's distro, or refused (one distro per fleet).
    ros: RobotRos | None = None


class RobotTemplate(Strict):
    """Robots added by `ccrp fleet scale N` are named <prefix><k>, k = 1, 2, ..."""

    prefix: Annotated[str, Field(pattern=r"^[a-z][a-z0-9]{0,24}$")] = "robot"
    type: RobotType = "generic"
    exports: list[Topic] = []
    imports: dict[Name, list[Topic]] = {}
    max: Annotated[StrictInt, Field(ge=1, le=1000)] = 50
    autostop: Autostop | None = None
    software: Software | None = None
    ros: RobotRos | None = None


class RosSettings(Strict):
    # One distro for the whole fleet, robots and clones alike (snapshots/<distro>.yaml): ROS 1
    # Noetic, or ROS 2 Jazzy or Kilted from the ros-<distro>-* wheels. Noetic when not given, so an
    # inventory written before `ccrp init` chose Jazzy keeps its distro.
    distro: Distro = "noetic"
    master_port: Port = 11311  # ROS 1 only
    # The recipe's platform the clones run (snapshots/<distro>.yaml `platforms:`); default: the
    # backend's (debian-bookworm). ubuntu-noble-ros: your image with ROS 2 installed (clouds).
    platform: Annotated[str, Field(pattern=r"^[a-z0-9][a-z0-9-]{0,39}$")] | None = None

    @property
    def ros2(self) -> bool:
        from ..recipes import is_ros2

        return is_ros2(self.distro)


class VpnSettings(Strict):
    port: Port = 1194
    proto: Literal["udp", "tcp"] = "udp"
    pool: ipaddress.IPv4Network = ipaddress.IPv4Network("10.80.0.0/16")
    subnet_prefix: Annotated[StrictInt, Field(ge=16, le=29)] = 24
    key_type: Literal["ecdsa-p256", "rsa3072"] = "ecdsa-p256"
    cert_days: Annotated[StrictInt, Field(ge=30, le=3650)] = 1095
    crl_days: Annotated[StrictInt, Field(ge=365, le=3650)] = 730

    @model_validator(mode="after")
    def _prefix_inside_pool(self) -> "VpnSettings":
        if self.subnet_prefix <= self.pool.prefixlen:
            raise ValueError(
                f"subnet_prefix /{self.subnet_prefix} must be longer than the pool's /{self.pool.prefixlen}"
            )
        return self


class CommonNetwork(Strict):
    cidr: ipaddress.IPv4Network = ipaddress.IPv4Network("10.90.0.0/24")
    # Clone k gets host first_host + k - 1: low addresses are left to gateways and DHCP.
    first_host: Annotated[StrictInt, Field(ge=2)] = 10


# multimaster_fkie is not packaged by Debian, and every clone runs Debian 12 (ProviderInfo.platform).
FKIE_REFUSED = ("fkie needs multimaster_fkie, available only for ROS 1 on Ubuntu 20.04 from packages.ros.org; "
                "ccrp's clones run Debian 12, which does not package it: use engine: relay")


class Sharing(Strict):
    # Topic sharing between clones is ccrp's relay agent (docs/sharing.md).
    engine: Literal["relay"] = "relay"
    relay_port: Port = 7447

    @field_validator("engine", mode="before")
    @classmethod
    def _no_fkie(cls, engine: object) -> object:
        if engine == "fkie":
            raise ValueError(FKIE_REFUSED)
        return engine


class SnapshotSettings(Strict):
    # `snapshot build`/`bake` keep this many of the newest snapshots, and any a clone runs from.
    keep: Annotated[int, Field(strict=True, ge=1, le=100)] = 2


class Inventory(Strict):
    fleet: Name
    # Each backend's settings model lives in its own package (providers/<kind>/settings.py): the
    # loader validates this section with the one the registry gives for its kind (inventory_model).
    provider: ProviderSettings
    ros: RosSettings = RosSettings()
    vpn: VpnSettings = VpnSettings()
    common: CommonNetwork = CommonNetwork()
    sharing: Sharing = Sharing()
    robots: list[Robot] = []
    template: RobotTemplate | None = None
    snapshots: SnapshotSettings = SnapshotSettings()
    # Fleet-wide; a robot's (or the template's) own `autostop` replaces it. Off when not given.
    autostop: Autostop | None = None
    # Fleet-wide; a robot's own `services.<name>` replaces the fleet's.
    services: Services = Services()
    # The robot's own software on its clone (docs/workloads.md): fleet-wide, then per robot type
    # and per robot, merged in that order.
    software: Software | None = None
    types: dict[RobotType, TypeSettings] = {}

    def software_of(self, robot: Robot) -> Software:
        """What robot's clone runs: the fleet's software, its type's, its own."""
        kind = self.types.get(robot.type)
        return merge(self.software, kind.software if kind else None, robot.software)

    def snapshot_software(self) -> Software:
        """What the fleet's snapshot holds: every package any robot needs and the workspace (one
        snapshot serves every clone; which nodes run is each robot's own)."""
        levels = [self.software, *(t.software for t in self.types.values()), *(r.software for r in self.robots),
                  self.template.software if self.template else None]
        merged = merge(*levels)
        return merged.model_copy(update={"run": []})

    def api_manager_of(self, robot: Robot) -> ApiManager | None:
        """The robot's API manager setting (its own, else the fleet's); None when off."""
        setting = robot.services.api_manager or self.services.api_manager
        return setting if setting is not None and setting.enabled else None

    def datasets_of(self, robot: str, members: list[str] | None = None) -> dict[str, list[str]]:
        """The datasets robot's clone shares: name -> the robots sharing it among `members` (the
        fleet's robots; by default those the inventory names). A dataset with no other member is
        left out: there is nobody to share it with."""
        k = self.services.knowledge
        if k is None:
            return {}
        names = [r.name for r in self.robots] if members is None else list(members)
        out = {}
        for ds, d in sorted(k.datasets.items()):
            group = names if d.robots == "all" else [n for n in names if n in d.robots]
            if robot in group and len(group) > 1:
                out[ds] = group
        return out

    @property
    def clone_platform(self) -> str:
        """The recipe's platform the clones run (snapshots/<distro>.yaml `platforms:`): `ros.platform`,
        else the backend's (its ProviderInfo.platform)."""
        return self.ros.platform or self.provider.platform

    def may_share_knowledge(self, robot: str) -> bool:
        """Whether robot's clone may take part in knowledge sync (its firewall opens the port)."""
        k = self.services.knowledge
        return k is not None and any(d.robots == "all" or robot in d.robots for d in k.datasets.values())

    def idle_of(self, robot: Robot) -> int:
        """Seconds of absence after which the robot's clone stops itself; 0: never."""
        setting = robot.autostop or self.autostop
        return setting.idle if setting else 0

    @field_validator("robots")
    @classmethod
    def _unique_names(cls, robots: list[Robot]) -> list[Robot]:
        seen: set[str] = set()
        for robot in robots:
            if robot.name in seen:
                raise ValueError(f"duplicate robot name {robot.name!r}")
            seen.add(robot.name)
        return robots

    @model_validator(mode="after")
    def _networks_disjoint(self) -> "Inventory":
        nets = {"vpn.pool": self.vpn.pool, "common.cidr": self.common.cidr, **self.provider.networks()}
        items = list(nets.items())
        for i, (name_a, a) in enumerate(items):
            for name_b, b in items[i + 1 :]:
                if a.overlaps(b):
                    raise ValueError(f"{name_a} {a} overlaps {name_b} {b}")
        return self

    @model_validator(mode="after")
    def _platform_known(self) -> "Inventory":
        from ..recipes import recipe

        name = self.ros.platform
        if name is None:
            return self
        platforms = recipe(self.ros.distro).platforms
        if name not in platforms:
            raise ValueError(f"ros.platform {name} is not one of ros.distro {self.ros.distro}'s ({', '.join(platforms)})")
        if platforms[name].clouds_only and not self.provider.bakes:
            # Baked from the user's own image: a backend that bakes nothing runs the others only.
            raise ValueError(f"ros.platform {name} is for clouds (baked from your own image); {self.provider.kind} "
                             f"clones run {', '.join(n for n, p in platforms.items() if not p.clouds_only)}")
        return self

    @model_validator(mode="after")
    def _entry_made(self) -> "Inventory":
        """An entry gateway needs a backend that makes one (its ports: addressing.entry_port)."""
        if self.provider.entry == "gateway" and not self.provider.gateways:
            raise ValueError(f"provider.entry: gateway: the {self.provider.kind} backend makes no entry gateway "
                             "(its robots reach their clones on this host's networks)")
        return self

    @model_validator(mode="after")
    def _one_distro(self) -> "Inventory":
        """A robot runs its fleet's ROS distro: its clone is built for that one distro, and a ROS 1
        robot cannot reach a ROS 2 clone at all (nor a Humble robot confine its discovery as a
        Jazzy clone expects: docs/ros2.md). Said per robot, per type or for the template."""
        d = self.ros.distro
        said = [(f"types.{t}", s.ros) for t, s in self.types.items()] + \
               [(f"robot {r.name!r}", r.ros) for r in self.robots] + [("template", self.template.ros if self.template else None)]
        for where, ros in said:
            if ros is not None and ros.distro != d:
                raise ValueError(f"{where} runs ROS {ros.distro}, the fleet ros.distro {d}: a fleet has one distro, "
                                 "robots and clones alike; give those robots a fleet of their own")
        return self

    @model_validator(mode="after")
    def _sharing_consistent(self) -> "Inventory":
        names = {r.name for r in self.robots}
        exports = {r.name: set(r.exports) for r in self.robots}
        for robot in self.robots:
            for topic in robot.exports:
                head = topic.split("/")[1]
                if head in names and head != robot.name:
                    # Re-exporting another robot's namespace would relay in a loop.
                    raise ValueError(
                        f"robot {robot.name!r} exports {topic}, which is robot {head!r}'s namespace"
                    )
            for source, topics in robot.imports.items():
                if source == robot.name:
                    raise ValueError(f"robot {robot.name!r} imports from itself")
                if source not in names:
                    raise ValueError(f"robot {robot.name!r} imports from unknown robot {source!r}")
                for topic in topics:
                    if topic not in exports[source]:
                        raise ValueError(
                            f"robot {robot.name!r} imports {topic} from {source!r}, which does not export it"
                        )
        if self.template:
            for source, topics in self.template.imports.items():
                if source not in names:
                    raise ValueError(f"template imports from unknown robot {source!r}")
                missing = [t for t in topics if t not in exports[source]]
                if missing:
                    raise ValueError(f"template imports {missing[0]} from {source!r}, which does not export it")
            for robot in self.robots:
                if robot.name.startswith(self.template.prefix) and robot.name[len(self.template.prefix):].isdigit():
                    raise ValueError(
                        f"robot {robot.name!r} collides with template names {self.template.prefix}<k>"
                    )
        return self

    @model_validator(mode="after")
    def _knowledge_consistent(self) -> "Inventory":
        for robot in self.robots:
            if robot.services.knowledge is not None:
                raise ValueError(f"robot {robot.name!r}: services.knowledge is fleet-wide; give it at the top level")
        k = self.services.knowledge
        if k is None:
            return self
        if k.port in (self.sharing.relay_port, self.vpn.port, self.ros.master_port):
            raise ValueError(f"services.knowledge.port {k.port} is taken by the relay, the VPN or the ROS master")
        names = {r.name for r in self.robots}
        for ds, d in k.datasets.items():
            if d.robots == "all":
                continue
            for name in d.robots:
                if name not in names:
                    raise ValueError(f"dataset {ds!r} names unknown robot {name!r}")
            if len(set(d.robots)) != len(d.robots):
                raise ValueError(f"dataset {ds!r} names a robot twice")
        return self

    @model_validator(mode="after")
    def _one_workspace(self) -> "Inventory":
        """The workspace is built into the fleet's one snapshot, so it is fleet-wide; types and
        robots choose which of its nodes run."""
        given = [(f"types.{t}", s.software) for t, s in self.types.items()] + \
                [(f"robot {r.name!r}", r.software) for r in self.robots] + \
                [("template", self.template.software if self.template else None)]
        for where, software in given:
            if software is not None and software.workspace is not None:
                raise ValueError(f"{where}: software.workspace is fleet-wide (it is built into the fleet's snapshot); "
                                 "give it under the top-level software:, and choose each robot's nodes with run:")
        return self

    def robot(self, name: str) -> Robot | None:
        return next((r for r in self.robots if r.name == name), None)

