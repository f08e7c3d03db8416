"""Where templates/ and snapshots/ live: inside the wheel (ccrp_cli/_data) or in the source tree; the
agents' code (ccrp_cli/agent/), shipped to clones as files."""

from __future__ import annotations

from functools import cache
from pathlib import Path

_PKG = Path(__file__).resolve().parent


@cache
def data_dir(name: str) -> Path:
    for candidate in (_PKG / "_data" / name, _PKG.parent / name):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError(f"ccrp installation is missing its {name}/ directory")


def agent_source(name: str) -> str:
    """Code that runs on a clone (ccrp_cli/agent/<name>.py), shipped as a file."""
    return (_PKG / "agent" / f"{name}.py").read_text()
