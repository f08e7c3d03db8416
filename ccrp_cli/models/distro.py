"""ROS distros in the inventory: the fleet's `ros.distro`, and what a robot or a type says it runs."""

from __future__ import annotations

from typing import Annotated

from pydantic import AfterValidator, Field

from ..errors import shown
from .strict import Strict


def known_distro(distro: str) -> str:
    """A distro ccrp builds: one with a recipe (snapshots/<distro>.yaml, recipes.distros), whose
    `ros:` says ROS 1 or ROS 2 (docs/ros2.md: no master, discovery confined to the tunnel)."""
    from ..recipes import distros

    if distro not in distros():
        raise ValueError(f"{shown(distro)} is not a ROS distro ccrp builds ({', '.join(distros())}: "
                         "one recipe each in snapshots/)")
    return distro


Distro = Annotated[str, AfterValidator(known_distro)]


class RobotRos(Strict):
    """What ROS a robot (or every robot of a type) runs, when the inventory says: it must be the
    fleet's `ros.distro`. A robot cannot speak another distro than its clone: ROS 1 and ROS 2 do
    not talk at all, and two ROS 2 distros' messages and discovery are not promised to match."""

    # Any distro's name, known to ccrp or not (humble...): one that is not the fleet's is refused
    # as such (models/inventory.py _one_distro), which is the useful message.
    distro: Annotated[str, Field(pattern=r"^[a-z]{2,20}$")]
