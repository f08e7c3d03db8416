"""ccrp deploy: a changed workspace or `run` list onto the running clones (docs/workloads.md)."""

from __future__ import annotations

from typing import Annotated

import typer

from ..errors import InputError
from . import options, output


def deploy(
    inventory: options.Inventory,
    robot: Annotated[str | None, typer.Option("--robot", "-r", help="Only this robot's clone.")] = None,
    type_: Annotated[str | None, typer.Option("--type", help="Only the clones of robots of this type.")] = None,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Say what would change on each clone; build and "
                                                            "push nothing.")] = False,
    canary: Annotated[int, typer.Option("--canary", min=0, metavar="N",
                                        help="Deploy to N clones first; if one of them fails, change no other.")] = 0,
    max_parallel: Annotated[int | None, typer.Option("--max-parallel", min=1, metavar="K",
                                                     help="Change at most K clones at once (default: the "
                                                          "backend's limit).")] = None,
    rollback: Annotated[bool, typer.Option("--rollback", help="Put back the version the last deploy replaced "
                                                             "(each clone keeps it); the inventory is not read for "
                                                             "software.")] = False,
    build_on: Annotated[str, typer.Option("--build-on", metavar="auto|local|clone",
                                          help="Where the workspace is built: this host's Docker engine (local), "
                                               "one running clone of the deploy, in its image (clone); auto: local "
                                               "when an engine answers here, else a clone.")] = "auto",
    as_json: options.Json = False,
) -> None:
    """Put the inventory's workspace and `run` nodes on the running clones without re-creating them:
    built once in the clone image (here, or on one of the clones), pushed to each clone, the changed nodes restarted; a node
    that does not stay up puts its clone back on the previous version. apt/pip changes need a new
    snapshot and new clones. `--rollback` puts back on each clone the version its last deploy
    replaced (then the inventory and the clones differ until the next deploy)."""
    from ..ops import deploy as core
    from ..providers import get_provider

    fleet = options.open_fleet(inventory)
    core.targets(fleet, fleet.store.load_state(), robot, type_)  # a bad --robot / --type: exit 2 before anything
    if build_on not in core.BUILD_ON:
        raise InputError(f"--build-on {build_on!r}: give one of {', '.join(core.BUILD_ON)}")
    if rollback and canary:
        raise InputError("--rollback takes no --canary", hint="roll back one clone first with --robot")
    provider = get_provider(fleet.inventory)
    if rollback:
        if dry_run:
            items = core.rollback(fleet, provider, output.info, robot, type_, dry_run=True)
        else:
            with fleet.store.lock():
                items = core.rollback(fleet, provider, output.info, robot, type_, max_parallel=max_parallel)
    elif dry_run:
        items = core.deploy(fleet, provider, output.info, robot, type_, dry_run=True)
    else:
        with fleet.store.lock():
            items = core.deploy(fleet, provider, output.info, robot, type_, canary=canary, max_parallel=max_parallel,
                                build_on=build_on)
    raise typer.Exit(output.results(items, as_json))
