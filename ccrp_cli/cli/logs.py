"""ccrp logs: the journal of a robot's own nodes (or of one of ccrp's units) on its clone."""

from __future__ import annotations

import time
from typing import Annotated

import typer

from . import options, output


def logs(
    inventory: options.Inventory,
    robot: options.Robot,
    name: Annotated[str | None, typer.Argument(help="A node of the robot's software.run, or a ccrp unit "
                                                    "(relay, openvpn, rosmaster or graph, ...). Default: every node.")] = None,
    follow: Annotated[bool, typer.Option("--follow", "-f", help="Keep printing new lines until Ctrl-C.")] = False,
    since: Annotated[str | None, typer.Option("--since", help="Only lines of the last 10m, 2h, 1d...")] = None,
    lines: Annotated[int, typer.Option("--lines", "-n", min=1, max=10000, help="How many of the last lines.")] = 100,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line: time, unit, message.")] = False,
) -> None:
    """Show a node's log from robot's clone, through the provider (Docker exec or SSH): e.g.
    `ccrp logs --robot nao1 mapper -f`."""
    from ..models.values import parse_duration
    from ..providers import get_provider
    from ..services.workloads import FOLLOW_PAGE, log_units, read_journal

    since_s = parse_duration(since, "--since") if since else None
    fleet = options.open_fleet(inventory)
    units = log_units(fleet.inventory, fleet.robot(fleet.store.load_state(), robot), name)
    provider = get_provider(fleet.inventory)
    entries, cursor = read_journal(provider, robot, units, lines, since_s)
    _show(entries, as_json)
    try:
        full = False
        while follow:
            if not full:  # after a full page more is waiting: read on at once
                time.sleep(1.0)
            # Bounded pages: a node that logs faster than we poll costs lag, never our memory.
            entries, cursor = read_journal(provider, robot, units, FOLLOW_PAGE, cursor=cursor)
            full = len(entries) >= FOLLOW_PAGE
            _show(entries, as_json)
    except KeyboardInterrupt:  # the way to end --follow: not an interruption of anything
        pass


def _show(entries: list[dict], as_json: bool) -> None:
    """The clone's lines: with --json the exact text (JSON escapes control characters), for humans
    through output.line, which escapes them (a node's ESC]52 must not reach the terminal)."""
    import json

    for e in entries:
        if as_json:
            print(json.dumps(e), flush=True)
        else:
            output.line(f"{e['time'][:23]} {e['unit'].removesuffix('.service')}: {e['message']}")
