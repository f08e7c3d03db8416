"""ccrp fleet ..."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import typer

from . import options, output

if TYPE_CHECKING:
    from ..providers.base import Provider

app = typer.Typer(help="Whole-fleet operations.", no_args_is_help=True, rich_markup_mode=None)


@app.command()
def validate(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Check an inventory and show the fleet's address plan. Changes nothing."""
    from ..services import programs
    from ..services.workloads import snapshot_software

    fleet = options.open_fleet(inventory)
    inv = fleet.inventory
    # The software read and checked as `snapshot build` reads it (a node's program the clone lacks
    # is refused), and a warning per program ccrp cannot tell is there.
    software = snapshot_software(inv, fleet.path)
    for line in programs.check(inv, software.apt, software.workspace):
        output.warn(line)
    state = fleet.store.load_state()
    plan = fleet.plan(state)
    robots = {r.name: r for r in fleet.members(state)}
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



@app.command()
def up(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Create or reuse every robot's clone, in parallel (idempotent; safe to re-run after a crash)."""
    from ..ops.fleet import fleet_up

    fleet, provider = options.open_provider(inventory)
    raise typer.Exit(output.results(fleet_up(fleet, provider, output.info), as_json))


@app.command()
def scale(
    size: Annotated[int, typer.Argument(help="Total number of clones wanted.", min=0)],
    inventory: options.Inventory,
    as_json: options.Json = False,
) -> None:
    """Grow or shrink the fleet to SIZE clones with template robots (inventory robots always stay)."""
    from ..ops.fleet import fleet_scale

    fleet, provider = options.open_provider(inventory)
    items = fleet_scale(fleet, provider, size, output.info)
    raise typer.Exit(output.results(items, as_json))


@app.command()
def down(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Remove every container, network and volume ccrp created for the fleet (PKI and state stay)."""
    from ..ops.fleet import fleet_down

    fleet, provider = options.open_provider(inventory)
    removed = fleet_down(fleet, provider, output.info)
    if as_json:
        output.emit_json({"removed": removed})


@app.command()
def plan(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Show what `fleet up` would change, and the cloud quotas the clones it creates draw on. Read-only."""
    from ..ops import reconcile

    fleet, provider = options.open_provider(inventory)
    rows = reconcile.plan(fleet, provider)
    output.emit(rows, as_json, ["ROBOT", "ACTION", "ID", "VPN ENDPOINT", "SOFTWARE"],
                [(r["robot"], r["action"], r["provider_id"], r.get("endpoint") or "", r.get("software") or "") for r in rows])
    if not as_json:
        quota_table(provider, [r["robot"] for r in rows if r["action"] == "create"])


def quota_table(provider: Provider, creating: list[str]) -> None:
    """The quotas the clones to create draw on (limit, use, what they take), and the refusal
    `fleet up` would answer with when one is short (ccrp_cli/ops/quotas.py)."""
    from ..ops import quotas
    from ..errors import CcrpError

    try:
        found = quotas.uses(provider, creating)
    except CcrpError as exc:
        output.warn(f"cannot read the {provider.kind} quotas: {exc.one_line()}")
        return
    if not found:
        return
    output.table(
        ["QUOTA", "WHERE", "LIMIT", "USED", "PER CLONE", "THIS NEEDS", "FREE AFTER"],
        [(u.quota.name, u.quota.scope, f"{u.quota.limit:g}", f"{u.quota.used:g}", f"{u.quota.per_clone:g}",
          f"{u.need:g}", f"{u.after:g}" + (" (short)" if u.short else "")) for u in found],
        title=f"quotas: {len(creating)} clone{'s' * (len(creating) != 1)} to create",
    )
    refused = quotas.refusal(provider.kind, found, creating)
    if refused is not None:
        output.warn(f"`fleet up` would refuse, creating nothing: {refused.one_line()}")
