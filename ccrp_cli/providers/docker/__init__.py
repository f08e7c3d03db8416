"""The local Docker backend: a clone is a systemd container booted by cloud-init (NoCloud)."""

from ..base import Ability, ProviderInfo
from .settings import DockerSettings

INFO = ProviderInfo(
    kind="docker",
    settings=DockerSettings,
    factory=".docker.provider:DockerProvider",
    abilities=frozenset({Ability.LOCAL_BUILD, Ability.ROBOT_ATTACH, Ability.HOST_IMAGES}),
    user_data_limit=262_144,  # the NoCloud seed: kept at GCE's size
    user_data_gzip=False,
    sdk_modules=(("docker", "docker"),),
    secrets="volume",
    own_kernel=False,
    host_tools=(("mmdebstrap", "builds the base image when it is missing"),),
)
