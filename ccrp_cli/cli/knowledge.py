"""ccrp knowledge ...: datasets shared between clones (services.knowledge; docs/services.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from . import options, output

app = typer.Typer(help="Datasets kept the same on the clones that share them (services.knowledge).",
                  no_args_is_help=True, rich_markup_mode=None)

Dataset = Annotated[str, typer.Option("--dataset", "-d", help="Dataset name (services.knowledge.datasets).")]


def _open(inventory):
    from ..providers import get_provider

    fleet = options.open_fleet(inventory)
    return fleet, get_provider(fleet.inventory)


def _size(n: int) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


@app.command("list")
def list_(inventory: options.Inventory, robot: options.Robot, dataset: Dataset, as_json: options.Json = False) -> None:
    """The dataset's items on the robot's clone: name, sha256, size, origin (the clone that added it)."""
    from ..services import knowledge

    fleet, provider = _open(inventory)
    reply = knowledge.list_items(fleet, provider, robot, dataset)
    items = reply["items"]
    output.emit(items, as_json, ["NAME", "SHA256", "SIZE", "ORIGIN"],
                [(i["name"], i["sha256"][:16], _size(i["size"]), i["origin"]) for i in items])
    if not as_json:
        output.info(f"dataset {dataset!r} on cri-{robot}: {len(items)} items ({_size(reply['bytes'])}), "
                    f"{reply['tombstones']} deleted")


@app.command("add")
def add(inventory: options.Inventory, robot: options.Robot, dataset: Dataset,
        files: Annotated[list[Path], typer.Argument(help="Files to add (each named by its file name).")],
        as_json: options.Json = False) -> None:
    """Add files to the dataset on the robot's clone; its partners get them within seconds."""
    from ..services import knowledge

    fleet, provider = _open(inventory)
    added = knowledge.add_items(fleet, provider, robot, dataset, files)
    output.emit(added, as_json, ["NAME", "SHA256", "SIZE", "ORIGIN", "RESULT"],
                [(i["name"], i["sha256"][:16], _size(i["size"]), i["origin"], "added" if i["new"] else "already there")
                 for i in added])


@app.command("remove")
def remove(inventory: options.Inventory, robot: options.Robot, dataset: Dataset,
           items: Annotated[list[str], typer.Argument(help="Item names (every content of that name) or sha256s.")],
           as_json: options.Json = False) -> None:
    """Remove items from the dataset everywhere it is shared (a tombstone reaches the partners)."""
    from ..services import knowledge

    fleet, provider = _open(inventory)
    gone = knowledge.remove_items(fleet, provider, robot, dataset, items)
    output.emit(gone, as_json, ["REMOVED", "SHA256", "ORIGIN"], [(i["name"], i["sha256"][:16], i["origin"]) for i in gone])


@app.command("sync")
def sync(inventory: options.Inventory, robot: options.Robot, dataset: Dataset, as_json: options.Json = False) -> None:
    """Reconcile now: the robot's clone pulls its partners' indexes and fetches what it lacks."""
    from ..services import knowledge

    fleet, provider = _open(inventory)
    reply = knowledge.sync(fleet, provider, robot, dataset)
    data = {k: reply[k] for k in ("changed", "items", "tombstones", "bytes")}
    output.emit(data, as_json, ["DATASET", "CHANGED", "ITEMS", "DELETED", "SIZE"],
                [(dataset, data["changed"], data["items"], data["tombstones"], _size(data["bytes"]))])


@app.command("merge")
def merge(inventory: options.Inventory, robot: options.Robot, dataset: Dataset,
          out: Annotated[Path, typer.Option("--out", "-o", help="The merged bag to write (new: a file for ROS 1, "
                                                                "a rosbag2 directory for ROS 2).")],
          as_json: options.Json = False) -> None:
    """Merge the dataset's bags into one bag of the fleet's ROS, in time order, each message once: items named
    *.bag into a ROS 1 bag, or on a ROS 2 fleet *.mcap and *.db3 (rosbag2 storage files) into a rosbag2 directory."""
    from ..services import knowledge

    fleet, provider = _open(inventory)
    result = knowledge.merge(fleet, provider, robot, dataset, out)
    output.emit(result, as_json, ["BAGS", "MESSAGES", "DUPLICATES DROPPED", "TOPICS", "WRITTEN"],
                [(result["bags"], result["messages"], result["duplicates"], " ".join(result["topics"]), result["out"])])
