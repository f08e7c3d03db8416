"""ccrp snapshot ...: golden images clones are created from."""

from __future__ import annotations

from typing import Annotated

import typer

from . import options, output

app = typer.Typer(help="Golden images: build, capture, list, delete.", no_args_is_help=True, rich_markup_mode=None)
COLUMNS = ["ID", "NAME", "CREATED", "SOURCE", "SIZE MB"]



def _show(records, as_json: bool) -> None:
    data = [r.model_dump() for r in records]
    output.emit(data, as_json, COLUMNS, [(r["id"], r["name"], r["created"], r["source"], r["size_mb"]) for r in data])


@app.command()
def build(
    inventory: options.Inventory,
    if_missing: Annotated[bool, typer.Option("--if-missing", help="Keep the recorded snapshot if its image exists and holds the inventory's software.")] = False,
    bare: Annotated[bool, typer.Option("--bare", help="Only systemd + cloud-init: clones install the recipe at boot (slow; for comparison).")] = False,
    as_json: options.Json = False,
) -> None:
    """Build the golden clone image from the recipe in snapshots/ and record it for new clones."""
    from ..providers import Ability

    fleet, provider = options.open_provider(inventory, Ability.LOCAL_BUILD, "the golden image is baked in the cloud: `ccrp snapshot bake`")
    from ..ops.snapshots import snapshot_build

    record = snapshot_build(fleet, provider, output.info, if_missing, bare)
    _show([record], as_json)


@app.command()
def bake(
    inventory: options.Inventory,
    base_image: Annotated[str | None, typer.Option("--base-image", callback=options.cloud_name, help="Debian 12 image to start from (Glance name/id, GCE image path, AMI id or SSM parameter); default: the cloud's stock Debian 12 image.")] = None,
    timeout: Annotated[float, typer.Option(help="Seconds the builder may take to install the recipe.", min=60)] = 1800,
    as_json: options.Json = False,
) -> None:
    """Bake the cloud snapshot: a builder instance installs the recipe, is captured, then terminated."""
    from ..providers import Ability

    fleet, provider = options.open_provider(inventory, Ability.BAKE, "the golden image is built on this host: `ccrp snapshot build`")
    from ..ops.snapshots import snapshot_bake

    record = snapshot_bake(fleet, provider, output.info, base_image, timeout)
    output.info(f"snapshot {record.name} ({record.id}) recorded: new clones of fleet {fleet.name!r} start from it")
    _show([record], as_json)


@app.command()
def create(
    inventory: options.Inventory,
    robot: options.Robot,
    use: Annotated[bool, typer.Option("--use", help="Create new clones from this snapshot.")] = False,
    as_json: options.Json = False,
) -> None:
    """Capture a configured clone as a snapshot (its secrets volume is not included)."""
    from ..ops.snapshots import snapshot_create

    fleet, provider = options.open_provider(inventory)
    record = snapshot_create(fleet, provider, robot, use)
    _show([record], as_json)


@app.command("list")
def list_(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """List the fleet's snapshots, and who uses each (new clones, clones created from it)."""
    from ..ops.snapshots import in_use, users

    fleet, provider = options.open_provider(inventory)
    used = in_use(fleet.store.load_state())
    data = [r.model_dump() | {"in_use": users(r, used)} for r in provider.list_snapshots()]
    output.emit(data, as_json, [*COLUMNS, "IN USE"],
                [(r["id"], r["name"], r["created"], r["source"], r["size_mb"], ", ".join(r["in_use"]) or "-") for r in data],
                title=f"snapshots of fleet {fleet.name!r} (snapshots.keep: {fleet.inventory.snapshots.keep})")


@app.command()
def delete(
    inventory: options.Inventory,
    snapshot: Annotated[str, typer.Argument(callback=options.cloud_name, help="Snapshot id or name.")],
    force: Annotated[bool, typer.Option(help="Delete even the snapshot new clones use.")] = False,
) -> None:
    """Delete a snapshot."""
    from ..ops.snapshots import snapshot_delete

    fleet, provider = options.open_provider(inventory)
    snapshot_delete(fleet, provider, snapshot, force)
    output.info(f"deleted snapshot {snapshot}")
