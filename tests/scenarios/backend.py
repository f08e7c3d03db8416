"""What a scenario needs from a backend: an inventory written for this run, `ccrp` run as the user
types it, and what the backend still holds carrying the fleet's labels (must be nothing at the end).

One module per backend (backend_<kind>.py) exposes `open_backend(tmp_path, fleet) -> contextmanager
yielding a Backend`; leaving the context removes everything the backend's fake or engine made,
even when the scenario failed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[2]


def inventory_text(fleet: str, provider: str, common_cidr: str, vpn_pool: str, distro: str = "noetic") -> str:
    """The thesis lab in small: nao1 exports /faces (on ROS 2: the demo node's /chatter), nao2
    imports it; a template for `fleet scale`."""
    topic = "/faces" if distro == "noetic" else "/chatter"
    return f"""fleet: {fleet}
provider:
{provider.rstrip()}
ros:
  distro: {distro}
vpn:
  pool: {vpn_pool}
common:
  cidr: {common_cidr}
robots:
  - name: nao1
    type: nao
    exports: [{topic}]
  - name: nao2
    type: nao
    imports:
      nao1: [{topic}]
template:
  prefix: robot
  type: generic
  max: 4
"""


@dataclass
class Backend:
    kind: str
    inventory: Path
    home: Path  # CCRP_HOME of the run
    env: dict[str, str] = field(default_factory=dict)  # what the user's shell would export (OS_CLOUD...)
    # What the backend holds carrying the fleet's labels ("kind id" each); [] once `fleet down` ran.
    owned: Callable[[], list[str]] = lambda: []
    # Fault injection: name -> context manager factory ("quota", "zone", "storm").
    faults: dict[str, Callable] = field(default_factory=dict)
    # Docker network of this host simulated robots of a cloud fleet sit on (reaching public IPs).
    sim_network: str | None = None
    # In-process runner for backends whose fake cannot serve another process (None: subprocess).
    runner: Callable[..., subprocess.CompletedProcess] | None = None

    def ccrp(self, *args: str, timeout: float = 900) -> subprocess.CompletedProcess:
        if self.runner is not None:
            return self.runner(*args, timeout=timeout)
        env = {**os.environ, "CCRP_HOME": str(self.home), **self.env}
        env.pop("CCRP_INVENTORY", None)
        return subprocess.run([sys.executable, "-m", "ccrp_cli", *args], cwd=ROOT, env=env, capture_output=True,
                              text=True, timeout=timeout)


@contextmanager
def no_fault():
    yield


def free_cidr(within: str, prefix: int = 24, skip: int = 0) -> str:
    """A /prefix of `within` that no Docker network nor route of this machine uses (the
    backends' networks become Docker networks)."""
    import ipaddress
    import random

    from ccrp_cli.init import docker_subnets, host_ranges

    used = docker_subnets() + [ipaddress.IPv4Network(r) for r in host_ranges()]
    candidates = list(ipaddress.IPv4Network(within).subnets(new_prefix=prefix))
    random.shuffle(candidates)  # two runs side by side rarely pick the same
    free = [c for c in candidates if not any(c.overlaps(u) for u in used)]
    return str(free[skip])
