"""OpenStack backend (openstacksdk, clouds.yaml / OS_CLOUD); the SDK is imported on construction."""

from ..base import Ability, ProviderInfo
from .settings import OpenStackSettings

INFO = ProviderInfo(
    kind="openstack",
    settings=OpenStackSettings,
    factory="openstack.provider:OpenStackProvider",
    abilities=frozenset({Ability.BAKE, Ability.CONSOLE}),
    user_data_limit=49_149,  # Nova: 65,535 bytes once base64-encoded
    user_data_gzip=True,
    sdk_modules=(("openstack", "openstack"), ("paramiko", "openstack")),
)


def __getattr__(name: str):
    # The provider class (and with it the SDK glue) only when asked for by name.
    if name == "OpenStackProvider":
        from .provider import OpenStackProvider

        return OpenStackProvider
    raise AttributeError(name)
