"""OpenStack backend (openstacksdk, clouds.yaml / OS_CLOUD); the SDK is imported on construction."""

from ..base import Ability, ProviderInfo
from .settings import OpenStackSettings

INFO = ProviderInfo(
    kind="openstack",
    settings=OpenStackSettings,
    factory=".openstack.provider:OpenStackProvider",
    abilities=frozenset({Ability.BAKE}),
    user_data_limit=49_149,  # Nova: 65,535 bytes once base64-encoded
    user_data_gzip=True,
    sdk_modules=(("openstack", "openstack"), ("paramiko", "openstack")),
)
