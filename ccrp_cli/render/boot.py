"""What a clone service adds to every clone's user-data (docs/architecture.md, "Clone services"). A
service declares it (services/base.py CloneService.boot); render/cloudinit.py writes the base
(OpenVPN, ROS, the login user) and then each declaration it is handed, in the registry's order. It
lives in render/ because the services import render/ and render/ must not import them (a cycle): the
registry hands render the declarations. Imports nothing heavy: every service module imports it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from .files import BundleFile
    from .view import CloneView


def no_files(view: CloneView) -> list[BundleFile]:
    return []


@dataclass(frozen=True)
class Boot:
    """A service's part of the user-data. tests/unit/test_clone_services.py checks it against what is
    rendered."""

    # templates/systemd/<unit>, written and enabled (started) at first boot, after the base's units.
    units: tuple[str, ...] = ()
    # templates/systemd/<socket>.j2, rendered for the clone and enabled alone before any unit: the
    # port is systemd's before any of ccrp's services (and their users) run.
    sockets: tuple[str, ...] = ()
    # agent/<name>.py, in CCRP_LIB on every clone (their units run them with python3).
    agents: tuple[str, ...] = ()
    agent_mode: str = "0644"
    # Agents only a ROS 2 clone gets from its user-data: its image holds the wheels' venv alone,
    # while a ROS 1 snapshot has them (image_agents).
    ros2_agents: tuple[str, ...] = ()
    # agent/<name>.py in CCRP_LIB of every ROS 1 snapshot, whose recipe's pip list has their packages:
    # the Docker image's build and the clouds' bake put them there, handed them by the core
    # (ops/snapshots.py image_agents: a provider cannot import the services). A ROS 2 image holds none.
    image_agents: tuple[str, ...] = ()
    # Of those, what a clone of a bare image (a stock image installing the recipe at first boot) gets
    # in its user-data instead; an agent `fleet up` pushes with its service's files is not among them
    # (the snapshot's copy only spares that push, and a bare AWS clone's user-data has no room).
    bare_agents: tuple[str, ...] = ()
    # System users (no login, no home) its agents run as.
    users: tuple[str, ...] = ()
    # Its own files, made for the clone (dest: the path on the clone).
    files: Callable[[CloneView], list[BundleFile]] = no_files
