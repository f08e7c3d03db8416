"""Wheels for a Docker image's Python, fetched by this host so that the image build needs no index.

They are kept in a cache (`$CCRP_CACHE/wheels`, default `~/.cache/ccrp/wheels`): a second build
downloads nothing it already has and gets the same bytes, so Docker's layer cache holds for the
layers that install them. Without it every `snapshot build` downloaded about 200 MB again, and
rebuilt the `pip_source` packages into wheels whose bytes (their zip timestamps) changed each time,
which made Docker re-run the ROS 2 venv step of every build.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path

from ...errors import CcrpError

# Debian 12's CPython; pip takes only the platform tags it is given (eclipse-zenoh and OpenCV are
# tagged manylinux2014, the ros-jazzy-* wheels manylinux_2_28; bookworm's glibc 2.36 runs both).
WHEEL_PYTHON = "3.11"


def cache_dir() -> Path:
    """Where fetched wheels are kept: $CCRP_CACHE/wheels, else $XDG_CACHE_HOME/ccrp/wheels, else ~/.cache/ccrp/wheels."""
    root = os.environ.get("CCRP_CACHE") or os.path.join(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache", "ccrp")
    return Path(root) / "wheels" / f"cp{WHEEL_PYTHON.replace('.', '')}"


def fetch(requirements: list[str], platforms: tuple[str, ...], source: Sequence[str] = ()) -> dict[str, bytes]:
    """`wheels/<file>` -> content: the wheels of `requirements` and of all they require, for
    WHEEL_PYTHON on `platforms`, and `source` packages (PyPI has them as sources only) built into
    wheels here. Files come from the cache when there."""
    cache = cache_dir()
    cache.mkdir(parents=True, exist_ok=True)
    links = ["--find-links", str(cache)]  # pip prefers a link's file to the index's for the same wheel
    with tempfile.TemporaryDirectory() as tmp:
        if source:
            _pip(["wheel", "--quiet", "--no-deps", *links, "--wheel-dir", tmp, *source], source)
        tags = [arg for p in platforms for arg in ("--platform", p)]
        download = ["download", "--quiet", "--only-binary=:all:", "--python-version", WHEEL_PYTHON, *tags,
                    "--implementation", "cp", *links, "--find-links", tmp, "--dest", tmp, *requirements]
        # The cache alone first (no index: seconds instead of the index's round trips); the index
        # when the cache lacks something (a new pin, a first build).
        if not _pip([*download, "--no-index"], requirements, check=False):
            _pip(download, requirements)
        wheels = sorted(Path(tmp).glob("*.whl"))
        for wheel in wheels:
            _keep(wheel, cache)
        return {f"wheels/{wheel.name}": wheel.read_bytes() for wheel in wheels}


def _keep(wheel: Path, cache: Path) -> None:
    """Copy into the cache unless there; atomic, since two builds may fetch at once."""
    target = cache / wheel.name
    if target.exists():
        return
    fd, part = tempfile.mkstemp(dir=cache, prefix=f".{wheel.name}.")
    os.close(fd)
    try:
        shutil.copyfile(wheel, part)
        os.replace(part, target)
    finally:
        if os.path.exists(part):
            os.unlink(part)


def _pip(args: list[str], what: Sequence[str], check: bool = True) -> bool:
    proc = subprocess.run([sys.executable, "-m", "pip", *args], capture_output=True, text=True)
    if proc.returncode != 0 and check:
        last = ([ln for ln in proc.stderr.splitlines() if not ln.startswith("WARNING")] or ["?"])[-1]
        raise CcrpError(f"cannot download {', '.join(what)}: {last}", hint="check that PyPI (or your pip index) is reachable")
    return proc.returncode == 0
