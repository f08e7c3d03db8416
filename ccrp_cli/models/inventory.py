"""The inventory: a fleet's desired shape, loaded strictly from YAML."""

from __future__ import annotations

import ipaddress
from typing import Annotated, Literal, Union

from pydantic import Field, field_validator, model_validator

from ..providers import REGISTRY
from .names import Name, Topic
from .strict import Strict
from .values import CloudName, Port, StrictInt

RobotType = Literal["nao", "turtlebot", "generic"]


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


class RobotTemplate(Strict):
    """Robots added by `ccrp fleet scale N` are named <prefix><k>, k = 1, 2, ..."""

    prefix: Annotated[str, Field(pattern=r"^[a-z][a-z0-9]{0,24}$")] = "robot"
    type: RobotType = "generic"
    exports: list[Topic] = []
    imports: dict[Name, list[Topic]] = {}
    max: Annotated[StrictInt, Field(ge=1, le=1000)] = 50


class RosSettings(Strict):
    # ROS 1 Noetic is the first target (snapshots/noetic.yaml); ROS 2 distros come later.
    distro: Literal["noetic"] = "noetic"
    master_port: Port = 11311


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


# Each backend's settings model lives in its own package (providers/<kind>/settings.py); the
# registry collects them, so a new backend touches its package and one registry line.
Provider = Annotated[Union[tuple(i.settings for i in REGISTRY.values())], Field(discriminator="kind")]  # type: ignore[valid-type]


class Inventory(Strict):
    fleet: Name
    provider: Provider
    ros: RosSettings = RosSettings()
    vpn: VpnSettings = VpnSettings()
    common: CommonNetwork = CommonNetwork()
    sharing: Sharing = Sharing()
    robots: list[Robot] = []
    template: RobotTemplate | None = None

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
        nets = {"vpn.pool": self.vpn.pool, "common.cidr": self.common.cidr}
        if self.provider.kind == "docker":
            nets["provider.public_cidr"] = self.provider.public_cidr
        items = list(nets.items())
        for i, (name_a, a) in enumerate(items):
            for name_b, b in items[i + 1 :]:
                if a.overlaps(b):
                    raise ValueError(f"{name_a} {a} overlaps {name_b} {b}")
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

    def robot(self, name: str) -> Robot | None:
        return next((r for r in self.robots if r.name == name), None)
