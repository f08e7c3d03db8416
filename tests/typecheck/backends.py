"""Each backend satisfies the protocols of providers/base.py: Provider, and the protocol of each
ability its ProviderInfo declares. Never run, only type-checked ([tool.mypy] in pyproject.toml,
tests/unit/test_typecheck.py): a backend that drifts from a protocol (a method missing, renamed, or
with another signature) fails the check here, with the backend, the protocol and the member.
tests/unit/test_typecheck.py holds these functions to the registry, so a new backend or ability is
not left out."""

from __future__ import annotations

from ccrp_cli.providers.aws.provider import AwsProvider
from ccrp_cli.providers.base import Bake, Gateways, HostImages, LocalBuild, Provider, RobotAttach, RobotHost
from ccrp_cli.providers.docker.provider import DockerProvider
from ccrp_cli.providers.docker.robots import RobotContainers
from ccrp_cli.providers.gcp.provider import GcpProvider
from ccrp_cli.providers.libvirt.provider import LibvirtProvider
from ccrp_cli.providers.openstack.provider import OpenStackProvider


def docker(backend: DockerProvider) -> None:
    provider: Provider = backend
    local_build: LocalBuild = backend
    robot_attach: RobotAttach = backend
    host_images: HostImages = backend


def openstack(backend: OpenStackProvider) -> None:
    provider: Provider = backend
    bake: Bake = backend
    gateways: Gateways = backend


def gcp(backend: GcpProvider) -> None:
    provider: Provider = backend
    bake: Bake = backend
    gateways: Gateways = backend


def aws(backend: AwsProvider) -> None:
    provider: Provider = backend
    bake: Bake = backend
    gateways: Gateways = backend


def libvirt(backend: LibvirtProvider) -> None:
    provider: Provider = backend
    local_build: LocalBuild = backend
    robot_attach: RobotAttach = backend


def robot_host(host: RobotContainers) -> None:
    """Where every backend's simulated robots run (providers.robot_host)."""
    robots: RobotHost = host
