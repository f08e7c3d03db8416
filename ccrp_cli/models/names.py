"""Names that end up in GCE resource names, DNS labels, ROS names and file names."""

from __future__ import annotations

import re
from typing import Annotated

from pydantic import StringConstraints

# The one alphabet valid at once for GCE names, DNS labels and ROS names: see docs/inventory.md.
NAME_PATTERN = r"^[a-z][a-z0-9]{0,30}$"
NAME_RE = re.compile(NAME_PATTERN)
# An absolute ROS graph name for a shared topic.
TOPIC_PATTERN = r"^(/[A-Za-z][A-Za-z0-9_]*)+$"

Name = Annotated[str, StringConstraints(pattern=NAME_PATTERN)]
# Bounded so that a topic echoed in an error (imports X, which is not exported) stays one short line.
Topic = Annotated[str, StringConstraints(pattern=TOPIC_PATTERN, max_length=200)]


def clone_host(robot: str) -> str:
    """Hostname of a robot's clone (README: Concepts)."""
    return f"cri-{robot}"


def power_name(robot: str) -> str:
    """Common name of a robot's power device (its VPN client certificate and password): a dot is
    in no robot name, so it is no other robot's, clone's or relay's."""
    return f"{robot}.power"


def relay_name(robot: str, generation: int) -> str:
    """Common name of a clone's topic relay certificate: one per certificate issued, so that the
    agents can admit exactly the current ones."""
    return f"relay-{robot}-{generation}"


def check_name(value: str, what: str = "robot name") -> str:
    from ..errors import InputError, shown

    if not NAME_RE.fullmatch(value):  # match() lets "nao1\n" through: `$` matches before a final newline
        raise InputError(
            f"invalid {what} {shown(value)}: must match {NAME_PATTERN}",
            hint="lower-case letters and digits, starting with a letter, at most 31 characters",
        )
    return value
