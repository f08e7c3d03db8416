"""ccrp topics: the effective topic-sharing matrix of the fleet."""

from __future__ import annotations

from . import options, output


def topics(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Who exports which topic to whom, and the name it has on the importing clone."""
    from ..services.sharing import matrix

    fleet = options.open_fleet(inventory)
    rows = matrix(fleet, fleet.store.load_state())
    output.emit(rows, as_json, ["SOURCE", "TOPIC", "TO", "SEEN THERE AS"],
                [(r["source"], r["topic"], r["dest"] or "(nobody imports it)", r["as"] or "") for r in rows],
                title=f"topic sharing of fleet {fleet.name!r} (engine: {fleet.inventory.sharing.engine})")
