"""ccrp doctor."""

from __future__ import annotations

import typer

from . import options, output


def doctor(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Check SDKs, credentials, quotas, the snapshot and local tools for the fleet. Changes nothing."""
    from ..ops import doctor as core

    checks = core.run(options.open_fleet(inventory))
    output.emit(core.as_dicts(checks), as_json, ["CHECK", "STATUS", "DETAIL", "FIX"],
                [(c.check, c.status, c.detail, c.hint) for c in checks])
    raise typer.Exit(1 if any(c.status == core.FAIL for c in checks) else 0)
