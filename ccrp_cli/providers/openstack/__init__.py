"""OpenStack backend (openstacksdk, clouds.yaml / OS_CLOUD); the SDK is imported on construction."""

from .provider import OpenStackProvider

__all__ = ["OpenStackProvider"]
