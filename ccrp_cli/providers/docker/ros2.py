"""The ROS 2 layer of a Docker image (docs/ros2.md): ROS 2 from the ros-<distro>-* wheels on PyPI,
in a venv at /opt/ros/<distro> of a Debian 12 image. `ccrp snapshot build` of a ROS 2 fleet takes its
wheels (images.build_context) and the venv step (templates/docker/ros2-venv.j2)."""

from __future__ import annotations

from ...recipes import Platform
from ...templates import static
from . import wheels


def venv_context(plat: Platform) -> dict[str, bytes]:
    """The build-context files of the venv step (templates/docker/ros2-venv.j2): the wheels of the
    recipe's `pip` list and of everything they require (wheels.fetch, for the image's python on the
    recipe's `wheel_platforms`), its `pip_source` packages built into wheels here, so the image build needs no
    index and no compiler; and the ros2-setup script."""
    return wheels.fetch(plat.pip, tuple(plat.wheel_platforms), plat.pip_source) | {"ros2-setup": static("image/ros2-setup").encode()}
