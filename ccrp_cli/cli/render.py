"""ccrp render ...: the files a clone and a robot receive, without provisioning anything."""

from __future__ import annotations

from typing import Annotated

import typer

from . import options, output

app = typer.Typer(help="Render clone and robot files without provisioning.", no_args_is_help=True, rich_markup_mode=None)


@app.command("cloud-init")
def cloud_init(
    inventory: options.Inventory,
    robot: options.Robot,
    bare: Annotated[bool, typer.Option(help="Install packages at boot (bare base image, no snapshot).")] = False,
) -> None:
    """Print the clone's cloud-init user-data (no private key; checked against the provider's limit)."""
    from ..fleet import clone_view
    from ..render import cloudinit
    from ..services.registry import boots
    from ..providers import info

    fleet = options.open_fleet(inventory)
    view = clone_view(fleet, fleet.store.load_state(), robot)
    text = cloudinit.user_data(view, boots(), install_packages=bare)
    info(fleet.inventory.provider.kind).fit_user_data(text)
    typer.echo(text, nl=False)


@app.command("clone-secrets")
def clone_secrets(inventory: options.Inventory, robot: options.Robot, out: options.OutDir) -> None:
    """Write the secrets pushed to the clone after boot (server key+cert, CA, CRL, tls-crypt, password hash)."""
    from ..errors import cannot_write
    from ..fleet import clone_view
    from ..render import bundles

    fleet = options.open_fleet(inventory)
    state = fleet.store.load_state()
    view = clone_view(fleet, state, robot)
    files = bundles.clone_secrets(view, fleet.pki.credentials(robot))
    with cannot_write(out):
        bundles.write_bundle(out, files, {"fleet": fleet.name, "robot": robot, "kind": "clone-secrets"})
    output.info(f"wrote {len(files)} files for clone {view.addr.clone_host} to {out}")


@app.command()
def edge(
    inventory: options.Inventory,
    robot: options.Robot,
    out: options.OutDir,
    remote: Annotated[
        str | None, typer.Option(help="HOST[:PORT] the robot dials (default: the clone's recorded endpoint).")
    ] = None,
) -> None:
    """Write the robot's edge bundle: .ovpn profile, credentials, ROS env, hosts, chrony, units, install.sh."""
    from ..robot.robots import write_edge

    write_edge(options.open_fleet(inventory), robot, out, remote)
    output.info(f"wrote the edge bundle of robot {robot!r} to {out}; install it with `sudo {out}/install.sh`")
