"""ccrp robot ...: the robot side (edge bundle, simulated robots)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from . import options, output

app = typer.Typer(help="The robot side: edge bundle and simulated robots.", no_args_is_help=True, rich_markup_mode=None)


@app.command()
def bundle(
    name: Annotated[str, typer.Argument(help="Robot name.")],
    inventory: options.Inventory,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Directory (default $CCRP_HOME/<fleet>/edge/<robot>).")] = None,
    remote: Annotated[str | None, typer.Option(help="HOST[:PORT] the robot dials (default: its clone's endpoint).")] = None,
) -> None:
    """Write the robot's ready-to-install bundle (same content as `ccrp render edge`)."""
    from ..robots import write_edge

    fleet = options.open_fleet(inventory)
    path = write_edge(fleet, name, out or fleet.store.root / "edge" / name, remote)
    output.info(f"bundle for robot {name!r} in {path}; on the robot: `sudo ./install.sh`")
    typer.echo(str(path))


@app.command()
def sim(
    inventory: options.Inventory,
    robot: options.Robot,
    stop: Annotated[bool, typer.Option("--stop", help="Stop and remove the simulated robot.")] = False,
    wait: Annotated[float, typer.Option("--wait", help="Seconds to wait until the robot's VPN is up and its node is on its clone's master (0: don't wait).")] = 0,
    as_json: options.Json = False,
) -> None:
    """Run a simulated robot (container on the public network) with exactly its edge bundle."""
    from ..providers import get_provider
    from ..providers.docker import robots as sims
    from ..render.templates import static
    from ..robots import edge_files

    fleet = options.open_fleet(inventory)
    from ..errors import InputError

    if fleet.inventory.provider.kind != "docker":
        raise InputError("simulated robots run on the docker provider only")
    provider = get_provider(fleet.inventory)
    state = fleet.store.load_state()
    fleet.robot(state, robot)
    if stop:
        removed = sims.stop(provider, robot)
        output.info(f"simulated robot {robot!r} {'removed' if removed else 'was not running'}")
        return
    from ..clones import snapshot_image

    files, endpoint = edge_files(fleet, robot)
    t0 = time.monotonic()
    cid = sims.start(provider, robot, snapshot_image(state), files, static("edge/ccrp-demo-node"))
    output.info(f"simulated robot {robot!r} ({cid}) installed its bundle and dials {endpoint}")
    result = {"robot": robot, "container": cid, "endpoint": endpoint}
    if wait > 0:
        from ..status import wait_connected

        result |= wait_connected(provider, robot, wait)
        result["seconds"] = round(time.monotonic() - t0, 2)  # from container start to node registered
        output.info(f"robot {robot!r} connected in {result['seconds']:.1f} s; nodes on its clone: {', '.join(result['nodes'])}")
    if as_json:
        output.emit_json(result)
