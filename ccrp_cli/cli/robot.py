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
    network: Annotated[str | None, typer.Option("--network", callback=options.cloud_name, help="Docker network of this host the robot runs on (cloud fleets; default `bridge`). Docker fleets: always <fleet>-public.")] = None,
    as_json: options.Json = False,
) -> None:
    """Run a simulated robot (a container on this host) with exactly its edge bundle; it dials its
    clone over the public network as a real robot would."""
    from ..errors import InputError
    from ..providers import Ability, get_provider, info
    from ..providers.docker import robots as sims
    from ..providers.docker.host import DockerHost
    from ..render.templates import static
    from ..robots import edge_files

    fleet = options.open_fleet(inventory)
    kind = fleet.inventory.provider.kind
    own_network = Ability.ROBOT_SIM in info(kind).abilities  # the Docker fleet's own public network
    if own_network and network:
        raise InputError("--network is for cloud fleets", hint="simulated robots of a Docker fleet sit on <fleet>-public")
    state = fleet.store.load_state()
    fleet.robot(state, robot)
    host = get_provider(fleet.inventory) if own_network else DockerHost(fleet.name)
    if stop:
        removed = sims.stop(host, robot)
        output.info(f"simulated robot {robot!r} {'removed' if removed else 'was not running'}")
        return
    from ..clones import snapshot_image

    files, endpoint = edge_files(fleet, robot)
    if own_network:
        image, net = snapshot_image(state), host.public_net
    else:
        image, net = sims.sim_image(host, fleet.inventory.ros.distro, output.info), network or "bridge"
    t0 = time.monotonic()
    cid = sims.start(host, robot, image, files, static("edge/ccrp-demo-node"), net)
    output.info(f"simulated robot {robot!r} ({cid}) installed its bundle and dials {endpoint}")
    result = {"robot": robot, "container": cid, "endpoint": endpoint, "network": net}
    if wait > 0:
        from ..status import wait_connected

        clone_side = host if own_network else get_provider(fleet.inventory)
        result |= wait_connected(clone_side, robot, wait)
        result["seconds"] = round(time.monotonic() - t0, 2)  # from container start to node registered
        output.info(f"robot {robot!r} connected in {result['seconds']:.1f} s; nodes on its clone: {', '.join(result['nodes'])}")
    if as_json:
        output.emit_json(result)
