"""The one output path: JSON on stdout for --json, tables for humans; messages on stderr. What it
writes for humans goes through errors.printable: a clone's text (logs, failed steps, status cells)
must not drive the operator's terminal. JSON keeps the exact text (json escapes control characters)."""

from __future__ import annotations

import json
import sys
from collections.abc import Sequence
from typing import Any

from ..errors import CcrpError, Interrupted, printable


def err(message: str) -> None:
    print(printable(message), file=sys.stderr, flush=True)


def line(text: str) -> None:
    """One line on stdout for humans (`ccrp logs`): its control characters escaped, a newline in
    `text` included, so one message stays one line."""
    print(printable(text), flush=True)


def info(message: str) -> None:
    err(f"ccrp: {message}")


def warn(message: str) -> None:
    err(f"ccrp: warning: {message}")


def command_output(text: str) -> None:
    """What a command run on a clone printed (`ccrp clone exec`): exact into a pipe or a file, which
    asked for its bytes; on a terminal each line with its control characters escaped (line ends and
    tabs kept), as the clone's text everywhere else."""
    if sys.stdout.isatty():
        text = "\n".join(printable(part) for part in text.split("\n"))
    sys.stdout.write(text)
    sys.stdout.flush()


def emit_json(data: Any) -> None:
    json.dump(data, sys.stdout, indent=2, default=str)
    sys.stdout.write("\n")


def wants_json(args: Sequence[str]) -> bool:
    """Whether the command line asks for JSON: `--json` among ccrp's own arguments (those before a
    `--`, after which `clone exec` passes a command's). Read from the command line, not from the
    parsed option, so a command that fails while its options are parsed answers in JSON too."""
    args = list(args)
    return "--json" in (args[: args.index("--")] if "--" in args else args)


def failed(exc: CcrpError, as_json: bool) -> None:
    """A command that failed: its one line on stderr and, with --json, the error envelope on stdout
    ({"error": {"code": exit code, "message", "hint"}}), so a script reading stdout gets JSON either way."""
    err(f"ccrp: {exc.message}" if isinstance(exc, Interrupted) else f"ccrp: error: {exc.one_line()}")
    if as_json:
        emit_json(exc.envelope())


def table(columns: Sequence[str], rows: Sequence[Sequence[Any]], title: str | None = None) -> None:
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    t = Table(title=title, title_justify="left", box=None, header_style="bold", pad_edge=False)
    for col in columns:
        t.add_column(col)
    for row in rows:
        # Text, not str: rich would read `[link=...]` or `[red]` in a cell (a node's name, an
        # error a clone wrote) as markup and write its escape sequences; a Text is shown as it is.
        t.add_row(*(Text("" if v is None else printable(str(v))) for v in row))
    console = Console()
    if not console.is_terminal:  # pipes and files get whole cells, never "…"
        console.width = 100_000
    console.print(t)


def emit(data: Any, as_json: bool, columns: Sequence[str] = (), rows: Sequence[Sequence[Any]] = (),
         title: str | None = None) -> None:
    """Render `data` as JSON, or the human view given by columns/rows."""
    if as_json:
        emit_json(data)
    else:
        table(columns, rows, title)


def results(items: list, as_json: bool, title: str | None = None) -> int:
    """Per-robot results of a fan-out command; returns the exit code (0, 1 all failed, 3 partial).
    A robot "not started" (a canary failed before its turn) counts as failed."""
    data = [{"robot": r.robot, "action": r.action, "seconds": round(r.seconds, 2), "detail": r.detail,
             **({"sent_bytes": r.sent_bytes} if r.sent_bytes is not None else {})} for r in items]
    emit(data, as_json, ["ROBOT", "RESULT", "TIME", "DETAIL"], [r.row() for r in items], title)
    failed = sum(r.action in ("failed", "not started") for r in items)
    if failed == 0:
        return 0
    return 1 if failed == len(items) else 3
