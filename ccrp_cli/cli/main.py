"""The `ccrp` command: `ccrp <object> <action>`."""

from __future__ import annotations

import functools
import sys
from typing import Annotated

import click
import typer
import typer.main

from .. import __version__
from ..errors import BAD_INPUT, CcrpError, InputError, Interrupted
from . import bench, clone, dashboard, deploy, doctor, fleet, gc, init, knowledge, logs, render, robot, snapshot, status, topics, vpn
from .output import failed, wants_json

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
    """Console entry point: every failure a user can cause ends in one line on stderr (and, with
    --json, in the error envelope on stdout: output.failed)."""
    try:
        try:
            # Without standalone mode, `raise typer.Exit(n)` in a command comes back as a return value.
            code = command()(standalone_mode=False)
            sys.exit(code if isinstance(code, int) else 0)
        except typer.Exit as exc:
            sys.exit(exc.exit_code)
        except CcrpError as exc:
            error = exc
        except (typer.Abort, KeyboardInterrupt):
            error = Interrupted()
        except typer.TyperException as exc:  # usage errors from the parser
            error = _usage_error(exc)
            if error is None:  # a command group without its command: its help
                sys.exit(BAD_INPUT)
        failed(error, wants_json(sys.argv[1:]))
        sys.exit(error.code)
    finally:
        _close_providers()


def _close_providers() -> None:
    """The providers the command opened (their SSH sessions, API clients), closed as it ends,
    whichever way; only if the command made one (a parse error loads no provider package)."""
    providers = sys.modules.get("ccrp_cli.providers")
    if providers is not None:
        providers.close_opened()


def _usage_error(exc: typer.TyperException) -> CcrpError | None:
    """A usage error from the parser as a failure (exit 2 when it names the command, else the
    parser's own code); None after printing the help of a group called without its command."""
    ctx = getattr(exc, "ctx", None)
    if type(exc).__name__ == "NoArgsIsHelpError" and ctx is not None:
        typer.echo(ctx.get_help())
        return None
    if ctx is None:
        return CcrpError(exc.format_message(), code=exc.exit_code)
    return InputError(f"{exc.format_message()} (see `{ctx.command_path} --help`)")
