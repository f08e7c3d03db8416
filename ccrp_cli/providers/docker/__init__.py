"""The local Docker backend: a clone is a systemd container booted by cloud-init (NoCloud)."""

from ..base import Ability, InitSection, ProviderInfo
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
    # `ccrp init`: no account to name; simulated robots dial the fleet's network of this host.
    init=InitSection(
        lines="  kind: docker                  # clones are containers on this host\n"
              "  public_cidr: {public}     # <fleet>-public: what simulated robots dial",
        public_pool=True, autostop=False, default=True),
    host_networks=".docker.host_networks:subnets",
    reach="engine",
    reach_is_credential=True,  # the engine answering is all there is
)
