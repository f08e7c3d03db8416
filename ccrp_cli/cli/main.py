"""The `ccrp` command: `ccrp <object> <action>`."""

from __future__ import annotations

import functools
import sys
from typing import Annotated

import click
import typer
import typer.main

from .. import __version__
from ..errors import BAD_INPUT, CcrpError
from . import bench, clone, dashboard, deploy, doctor, fleet, gc, init, knowledge, logs, render, robot, snapshot, status, topics, vpn

app = typer.Typer(
    name="ccrp",
    help="Clone-based Cloud Robotic Platform: one cloud clone per robot, ROS over a per-robot VPN.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    # Plain help: rich's help renderer alone costs ~55 ms of every `ccrp --help`.
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)
app.add_typer(clone.app, name="clone")
app.add_typer(fleet.app, name="fleet")
app.add_typer(robot.app, name="robot")
app.add_typer(vpn.app, name="vpn")
app.add_typer(snapshot.app, name="snapshot")
app.add_typer(render.app, name="render")
app.add_typer(bench.app, name="bench")
app.add_typer(knowledge.app, name="knowledge")
app.command("init")(init.init)
app.command("status")(status.status)
app.command("gc")(gc.gc)
app.command("doctor")(doctor.doctor)
app.command("topics")(topics.topics)
app.command("logs")(logs.logs)
app.command("deploy")(deploy.deploy)
app.command("dashboard")(dashboard.dashboard)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"ccrp {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show the version and exit.")
    ] = False,
) -> None:
    pass


@functools.cache
def command() -> click.Command:
    """The parser, built once per process: Typer reads every command's signature and type hints
    to build it (about 65 ms), which a process running ccrp many times (the dashboard, the tests'
    in-process runs) would pay at each call."""
    return typer.main.get_command(app)


def run() -> None:
    """Console entry point: every failure a user can cause ends in one line on stderr."""
    try:
        # Without standalone mode, `raise typer.Exit(n)` in a command comes back as a return value.
        code = command()(standalone_mode=False)
        sys.exit(code if isinstance(code, int) else 0)
    except CcrpError as exc:
        print(f"ccrp: error: {exc.one_line()}", file=sys.stderr)
        sys.exit(exc.code)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except (typer.Abort, KeyboardInterrupt):
        print("ccrp: interrupted; state on disk is consistent, run the command again to continue", file=sys.stderr)
        sys.exit(130)
    except typer.TyperException as exc:  # usage errors from the parser
        ctx = getattr(exc, "ctx", None)
        if type(exc).__name__ == "NoArgsIsHelpError" and ctx is not None:
            typer.echo(ctx.get_help())
            sys.exit(BAD_INPUT)
        where = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
        print(f"ccrp: error: {exc.format_message()}{where}", file=sys.stderr)
        sys.exit(BAD_INPUT if ctx is not None else exc.exit_code)
