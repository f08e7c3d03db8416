"""Options shared by commands."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

DEFAULT_INVENTORY = "ccrp.yaml"
_NOT_FOUND = Path()


def find_inventory() -> Path:
    """Without -i or CCRP_INVENTORY: ./ccrp.yaml, else the nearest one in a parent directory (as
    git finds its repository). Says on stderr which file it took."""
    here = Path.cwd()
    for directory in (here, *here.parents):
        candidate = directory / DEFAULT_INVENTORY
        if candidate.is_file():
            from . import output

            output.info(f"using inventory {candidate.relative_to(here) if directory == here else candidate}")
            return candidate
    return _NOT_FOUND


Inventory = Annotated[
    Path,
    typer.Option("--inventory", "-i", envvar="CCRP_INVENTORY", default_factory=find_inventory, show_default=False,
                 help=f"Fleet inventory YAML (default: ./{DEFAULT_INVENTORY} or the nearest one above)."),
]
Robot = Annotated[str, typer.Option("--robot", "-r", help="Robot name (its clone is cri-<robot>).")]
Json = Annotated[bool, typer.Option("--json", help="JSON on stdout (logs stay on stderr).")]
OutDir = Annotated[Path, typer.Option("--out", "-o", help="Directory to write (created 0700).")]


def cloud_name(value: str | None) -> str | None:
    """Option callback for an image, snapshot or network name handed to a cloud or Docker: one
    token (models/values.py), or exit 2 in one line before the fleet is opened."""
    if value is None:
        return None
    from ..models.values import check_cloud_name

    try:
        return check_cloud_name(value)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None


# The core (pydantic models, cryptography, yaml) is imported only when a command runs, so
# `ccrp --help` and completion stay fast.
def open_fleet(inventory: Path):
    """The fleet; its store names this command in the fleet lock, and says on stderr when it
    waits for another run's lock."""
    from ..errors import InputError
    from ..fleet import Fleet
    from . import output

    if inventory == _NOT_FOUND:
        raise InputError(f"no inventory: no -i, no CCRP_INVENTORY, and no {DEFAULT_INVENTORY} here or in a parent directory",
                         hint="write one with `ccrp init`, or pass -i FILE (examples in inventories/)")
    fleet = Fleet.open(inventory)
    fleet.store.command = command_name()
    fleet.store.on_wait = output.info
    return fleet


def command_name() -> str:
    """The command as typed after the program name, up to its first option (`fleet scale 5`).
    The console entry point (main.run) parses sys.argv, in-process runs included."""
    import sys

    words = []
    for arg in sys.argv[1:4]:
        if arg.startswith("-"):
            break
        words.append(arg)
    return " ".join(words)


def open_provider(inventory: Path, needs=None, otherwise: str = ""):
    """The fleet and its provider; with `needs` (an Ability), exit 2 first when the backend lacks it."""
    from ..providers import get_provider, require

    fleet = open_fleet(inventory)
    if needs is not None:
        kind = fleet.inventory.provider.kind
        require(kind, needs, hint=f"on {kind}, {otherwise}")
    return fleet, get_provider(fleet.inventory)
