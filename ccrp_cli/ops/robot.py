"""The verbs that act on a robot through its clone: `ccrp robot teleop` and `power`, and the
dashboard's drive keys and Power buttons. Neither takes the fleet lock: they change nothing ccrp
records, and an operator must not wait behind a scale. docs/architecture.md "Code map"."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ..robot.evaluation import send_command
from ..robot.power import power

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Lifecycle
    from .clones import Progress


def robot_teleop(fleet: Fleet, provider: Lifecycle, robot: str, linear: float, angular: float, topic: str = "cmd_vel",
                 timeout: float = 5.0, keep: bool = False) -> dict[str, Any]:
    """`ccrp robot teleop` and the dashboard's drive keys: one velocity command through the clone."""
    return send_command(fleet, provider, robot, linear, angular, topic, timeout, keep)


def robot_power(fleet: Fleet, robot: str, action: str, say: Progress, timeout: float = 30) -> dict[str, Any]:
    """`ccrp robot power on|off|status` and the dashboard's Power buttons: through the robot's clone
    to its power device, waiting for its report (a first use on a simulated robot issues its
    device's certificate under the fleet lock)."""
    return power(fleet, robot, action, say, timeout)
