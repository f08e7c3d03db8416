"""ccrp clone ...: one robot's clone."""

from __future__ import annotations

from typing import Annotated

import typer

from . import options, output

app = typer.Typer(help="One robot's clone: create, start, stop, restart, delete, list, exec.", no_args_is_help=True, rich_markup_mode=None)



@app.command()
def create(inventory: options.Inventory, robot: options.Robot, as_json: options.Json = False) -> None:
    """Create the robot's clone from the fleet's snapshot (idempotent: reuses an existing one)."""
    from ..ops.clone import clone_create

    fleet, provider = options.open_provider(inventory)
    raise typer.Exit(output.results(clone_create(fleet, provider, robot, output.info), as_json))


@app.command()
def start(inventory: options.Inventory, robot: options.Robot, as_json: options.Json = False) -> None:
    """Start the robot's stopped clone (stopped by autostop or in the cloud's console): its disk is as it
    was; ccrp pushes its keys again and waits until it serves. A running clone is left as it is."""
    from ..ops.clone import clone_start

    fleet, provider = options.open_provider(inventory)
    items = clone_start(fleet, provider, robot, output.info)
    raise typer.Exit(output.results(items, as_json))


@app.command()
def stop(inventory: options.Inventory, robot: options.Robot, as_json: options.Json = False) -> None:
    """Stop the robot's clone: it costs no compute while stopped, its disk and keys stay. `ccrp clone
    start` (or the next `fleet up`) starts it again. Stopped already: left as it is."""
    from ..ops.clone import clone_stop

    fleet, provider = options.open_provider(inventory)
    raise typer.Exit(output.results(clone_stop(fleet, provider, robot, output.info), as_json))


@app.command()
def restart(inventory: options.Inventory, robot: options.Robot, as_json: options.Json = False) -> None:
    """Stop the robot's clone and start it again, then wait until it serves: the cure for a clone
    that no longer answers, since the provider stops it, not the clone itself."""
    from ..ops.clone import clone_restart

    fleet, provider = options.open_provider(inventory)
    raise typer.Exit(output.results(clone_restart(fleet, provider, robot, output.info), as_json))


@app.command()
def delete(inventory: options.Inventory, robot: options.Robot, as_json: options.Json = False) -> None:
    """Delete the robot's clone and its secrets volume (the robot keeps its certificates and addresses)."""
    from ..ops.clone import clone_delete

    fleet, provider = options.open_provider(inventory)
    raise typer.Exit(output.results(clone_delete(fleet, provider, robot, output.info), as_json))


@app.command("list")
def list_(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """List the fleet's clones as the provider sees them (by ownership labels)."""
    fleet, provider = options.open_provider(inventory)
    records = [r.model_dump() for r in provider.query().values()]
    output.emit(records, as_json, ["ROBOT", "ID", "STATUS", "PUBLIC IP", "COMMON IP"],
                [(r["robot"], r["provider_id"], r["status"], r["public_ip"], r["common_ip"]) for r in records])


@app.command(name="exec", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def exec_(
    inventory: options.Inventory,
    robot: options.Robot,
    command: Annotated[list[str], typer.Argument(help="Command and arguments, after --.")],
    timeout: Annotated[float, typer.Option(help="Seconds before the command is killed.")] = 600,
    as_node: Annotated[bool, typer.Option("--as-node", help="Run it as the clone's nodes run: their user, the clone's ROS "
                                                            "environment and the workspace's (its message types; on ROS 2, "
                                                            "root does not hear the nodes' shared-memory DDS).")] = False,
) -> None:
    """Run a command inside the robot's clone: ccrp clone exec -i INV --robot nao1 -- rostopic list"""
    fleet = options.open_fleet(inventory)
    fleet.robot(fleet.store.load_state(), robot)  # a robot the fleet does not have is bad input
    from ..providers import get_provider

    if as_node:
        from ..services.workloads import AS_NODE

        command = [*AS_NODE, *command]
    rc, out = get_provider(fleet.inventory).transport.exec(robot, command, timeout=timeout)
    output.command_output(out)
    raise typer.Exit(rc)
