"""ccrp gc."""

from __future__ import annotations

from typing import Annotated

import typer

from . import options, output


def gc(
    inventory: options.Inventory,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Only list the leaks.")] = False,
    unlabelled: Annotated[bool, typer.Option("--unlabelled", help="Docker: also remove snapshot images from before "
                                             "images were labelled with their state, when no container uses them.")] = False,
    as_json: options.Json = False,
) -> None:
    """Delete resources carrying the fleet's labels that ccrp's state does not know (leaks).

    Known: recorded clones, their public IPs/volumes/routes, the fleet's network, firewall and key
    pair, and its snapshots. On Docker, also snapshot images of any fleet whose state directory
    is gone (orphans). Run with --dry-run first to see what would go."""
    from ..ops.gc import gc

    fleet, provider = options.open_provider(inventory)
    leaks, images = gc(fleet, provider, dry_run, unlabelled, output.info)
    results = leaks + images
    output.emit([r.as_dict() for r in results], as_json, ["KIND", "ID", "NAME", "ROBOT", "RESULT", "DETAIL"],
                [(r.resource.kind, r.resource.id, r.resource.name, r.resource.robot, r.action, r.detail) for r in results])
    if not as_json:
        orphans = sum(r.action in ("orphan", "deleted", "failed") for r in images)
        output.info(f"fleet {fleet.name!r}: {len(leaks)} leaked resources"
                    + (f"; {orphans} orphan snapshot images on this host" if images else "")
                    + (" (dry run: nothing deleted)" if dry_run else ""))
        if any(r.action == "unlabelled" for r in images):
            output.info("unlabelled: snapshot images from before ccrp labelled them with their state directory; "
                        "`ccrp gc --unlabelled` removes those no container uses and no state here records")
    raise typer.Exit(1 if any(r.action == "failed" for r in results) else 0)
