"""ccrp fleet ..."""

from __future__ import annotations

import typer

from ..fleet import Fleet
from . import options, output

app = typer.Typer(help="Whole-fleet operations.", no_args_is_help=True)


@app.command()
def validate(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Check an inventory and show the fleet's address plan. Changes nothing."""
    fleet = Fleet.open(inventory)
    inv = fleet.inventory
    plan = fleet.plan(fleet.store.load_state())
    robots = {r.name: r for r in fleet.members(fleet.store.load_state())}
    data = {
        "fleet": inv.fleet,
        "provider": inv.provider.kind,
        "ros_distro": inv.ros.distro,
        "sharing_engine": inv.sharing.engine,
        "robots": [
            {
                "name": name,
                "type": robots[name].type,
                "clone": a.clone_host,
                "vpn_subnet": str(a.vpn_subnet),
                "clone_vpn_ip": str(a.clone_vpn_ip),
                "robot_vpn_ip": str(a.robot_vpn_ip),
                "common_ip": str(a.common_ip),
                "exports": robots[name].exports,
                "imports": robots[name].imports,
            }
            for name, a in plan.items()
        ],
    }
    if not as_json:
        output.info(
            f"{inventory}: fleet {inv.fleet!r} is valid ({inv.provider.kind}, ROS {inv.ros.distro}, "
            f"{len(plan)} robots, {inv.sharing.engine} sharing)"
        )
    output.emit(
        data, as_json,
        ["ROBOT", "TYPE", "CLONE", "VPN SUBNET", "ROBOT IP", "COMMON IP"],
        [(r["name"], r["type"], r["clone"], r["vpn_subnet"], r["robot_vpn_ip"], r["common_ip"]) for r in data["robots"]],
    )
