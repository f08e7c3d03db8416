"""ccrp logs: the journal of robots' own nodes (or of one of ccrp's units) on their clones, merged
by time across robots and nodes, each line labelled robot/node as `docker compose logs` does."""

from __future__ import annotations

import os
import sys
import time
from typing import Annotated

import typer

from . import options, output

# A prefix's colour on a terminal, by robot/node in the order they first print (as docker compose).
COLOURS = ("36", "33", "32", "35", "34", "96", "93", "92", "95", "94")


def logs(
    inventory: options.Inventory,
    name: Annotated[str | None, typer.Argument(help="A node of the robots' software.run, or a ccrp unit "
                                                    "(relay, openvpn, rosmaster or graph, ...). Default: every node.")] = None,
    robot: Annotated[str | None, typer.Option("--robot", "-r", help="These robots' clones: R or R1,R2,...")] = None,
    type_: Annotated[str | None, typer.Option("--type", help="The clones of the robots of this type.")] = None,
    every: Annotated[bool, typer.Option("--all", help="Every robot's clone.")] = False,
    follow: Annotated[bool, typer.Option("--follow", "-f", help="Keep printing new lines until Ctrl-C.")] = False,
    since: Annotated[str | None, typer.Option("--since", help="Only lines of the last 10m, 2h, 1d...")] = None,
    lines: Annotated[int, typer.Option("--lines", "-n", min=1, max=10000, help="How many of each node's last lines.")] = 100,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per line: robot, node, time, message.")] = False,
) -> None:
    """Show nodes' logs from the robots' clones through the provider (Docker exec or SSH), merged by
    time: e.g. `ccrp logs --robot nao1 mapper -f`, `ccrp logs --all --since 10m`."""
    from ..models.values import parse_duration
    from ..ops import logs as core
    from ..providers import get_provider

    since_s = parse_duration(since, "--since") if since else None
    fleet = options.open_fleet(inventory)
    state = fleet.store.load_state()
    readers = core.readers(fleet, state, core.select(fleet, state, robot, type_, every), name)
    run = core.Logs(get_provider(fleet.inventory), readers, lines, since_s, follow, output.warn)
    show = _json if as_json else Lines(readers).show
    try:
        code = run.run(show, time.sleep)
    except KeyboardInterrupt:  # the way to end --follow: not an interruption of anything
        if not follow:
            raise
        code = 0
    raise typer.Exit(code)


def _json(records: list[dict]) -> None:
    """The exact text, JSON-escaped (control characters included)."""
    import json

    for r in records:
        print(json.dumps(r), flush=True)


class Lines:
    """For humans: `robot/node | time message`, the prefixes padded to one width; the text through
    errors.printable, which escapes control characters (a node's ESC]52 must not reach the
    terminal); the prefix coloured on a terminal only (and not under NO_COLOR)."""

    def __init__(self, readers) -> None:
        from ..ops.logs import node_of

        self.width = max(len(f"{r.robot}/{node_of(u)}") for r in readers for u in r.units)
        self.colours: dict[str, str] = {}
        self.tty = sys.stdout.isatty() and not os.environ.get("NO_COLOR")

    def show(self, records: list[dict]) -> None:
        from ..errors import printable

        for r in records:
            label = printable(f"{r['robot']}/{r['node']}")
            self.width = max(self.width, len(label))  # systemd's own unit names, a ccrp unit...
            prefix = f"{label:<{self.width}} | "
            if self.tty:
                colour = self.colours.setdefault(label, COLOURS[len(self.colours) % len(COLOURS)])
                prefix = f"\x1b[{colour}m{label:<{self.width}}\x1b[0m | "
            print(prefix + printable(f"{r['time'][:23]} {r['message']}"), flush=True)
