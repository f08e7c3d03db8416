"""The local Docker backend: a clone is a systemd container booted by cloud-init (NoCloud)."""

from .provider import DockerProvider

__all__ = ["DockerProvider"]
