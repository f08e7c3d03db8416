"""Shared fixtures: an isolated CCRP_HOME, the lab fleet with its PKI, and a CLI runner."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAB = ROOT / "inventories" / "lab.yaml"
INVENTORIES = sorted((ROOT / "inventories").glob("*.yaml"))


@pytest.fixture
def ccrp_home(tmp_path, monkeypatch) -> Path:
    home = tmp_path / "home"
    monkeypatch.setenv("CCRP_HOME", str(home))
    return home


def run_ccrp(*args: str, home: Path, cwd: Path = ROOT, check: bool = False) -> subprocess.CompletedProcess:
    env = {**os.environ, "CCRP_HOME": str(home)}
    env.pop("CCRP_INVENTORY", None)
    proc = subprocess.run(
        [sys.executable, "-m", "ccrp_cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"ccrp {' '.join(args)} failed ({proc.returncode}): {proc.stderr}")
    return proc


@pytest.fixture
def ccrp(ccrp_home):
    def _run(*args: str, check: bool = False) -> subprocess.CompletedProcess:
        return run_ccrp(*args, home=ccrp_home, check=check)

    return _run


@pytest.fixture
def lab(ccrp_home):
    """The lab fleet with its CA and certificates for every robot."""
    from ccrp_cli import vpn
    from ccrp_cli.fleet import Fleet

    fleet = Fleet.open(LAB)
    vpn.init(fleet)
    for robot in fleet.inventory.robots:
        vpn.issue(fleet, robot.name)
    return fleet
