"""The ROS 2 layer of a Docker image (docs/ros2.md): ROS 2 from the ros-<distro>-* wheels on PyPI,
in a venv at /opt/ros/<distro> of a Debian 12 image. `ccrp snapshot build` of a ROS 2 fleet takes its
wheels (images.build_context) and the same venv step (templates/docker/ros2-venv.j2); `dockerfile`
here is the plain layer without a clone's configuration (tests/e2e/test_ros2_discovery.py)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

from ...errors import CcrpError
from ...recipes import Platform
from ...render.templates import render, static

# Wheels for the image's python (Debian 12: CPython 3.11, glibc 2.36). pip takes only the platform
# tags it is given: eclipse-zenoh is tagged manylinux2014, the ros-jazzy-* wheels manylinux_2_28.
WHEEL_PYTHON = "3.11"
WHEEL_PLATFORMS = ("manylinux2014_x86_64", "manylinux_2_28_x86_64")


def dockerfile(distro: str, base_image: str, plat: Platform) -> str:
    """The recipe's packages, and its `pip` list (the ros-<distro>-* wheels) in a venv at
    /opt/ros/<distro> with a setup.sh for processes outside the venv. Its build context is
    `venv_context(plat)`."""
    return render("docker/ros2.Dockerfile.j2", distro=distro, base_image=base_image, packages=plat.packages,
                  pip=plat.pip, prefix=f"/opt/ros/{distro}")


def venv_context(plat: Platform) -> dict[str, bytes]:
    """The build-context files of the venv step (templates/docker/ros2-venv.j2): the wheels of the
    recipe's `pip` list and of everything they require, for the image's python (WHEEL_PYTHON,
    WHEEL_PLATFORMS), as `wheels/<name>`; its `pip_source` packages built into wheels here, so the
    image build needs no index and no compiler; and the ros2-setup script."""
    with tempfile.TemporaryDirectory() as tmp:
        if plat.pip_source:
            _pip(["wheel", "--quiet", "--no-deps", "--wheel-dir", tmp, *plat.pip_source], plat.pip_source)
        platforms = [arg for p in WHEEL_PLATFORMS for arg in ("--platform", p)]
        _pip(["download", "--quiet", "--only-binary=:all:", "--python-version", WHEEL_PYTHON, *platforms,
              "--implementation", "cp", "--find-links", tmp, "--dest", tmp, *plat.pip], plat.pip)
        wheels = {f"wheels/{wheel.name}": wheel.read_bytes() for wheel in sorted(Path(tmp).glob("*.whl"))}
    return wheels | {"ros2-setup": static("image/ros2-setup").encode()}


def _pip(args: list[str], what: list[str]) -> None:
    proc = subprocess.run([sys.executable, "-m", "pip", *args], capture_output=True, text=True)
    if proc.returncode != 0:
        last = ([ln for ln in proc.stderr.splitlines() if not ln.startswith("WARNING")] or ["?"])[-1]
        raise CcrpError(f"cannot download {', '.join(what)}: {last}", hint="check that PyPI (or your pip index) is reachable")
