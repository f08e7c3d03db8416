"""ccrp dashboard: the fleet in a browser (docs/dashboard.md)."""

from __future__ import annotations

from typing import Annotated

import typer

from . import options


def dashboard(
    inventory: options.Inventory,
    bind: Annotated[str, typer.Option(help="Address and port to listen on (loopback by default).")] = "127.0.0.1:8080",
    token: Annotated[str | None, typer.Option(
        envvar="CCRP_DASHBOARD_TOKEN", show_default=False,
        help="Access token (at least 16 characters, 8 of them different; default: a random one, "
             "printed in the URL to open). "
             "Prefer the environment variable: other users see command lines.")] = None,
    interval: Annotated[float, typer.Option(help="Seconds between two reads of the fleet's status.", min=1)] = 5.0,
) -> None:
    """Serve the fleet's live status, alerts and actions (clone start, vpn revoke, fleet scale) to a
    browser. Prints the URL to open, with its access token, on stderr; Ctrl-C stops it."""
    try:
        import fastapi  # noqa: F401
        import uvicorn  # noqa: F401
    except ImportError as exc:
        from ..errors import CcrpError

        raise CcrpError(f"ccrp dashboard needs {exc.name}, which is not installed",
                        hint="pip install 'ccrp[dashboard]' (fastapi and uvicorn)") from None
    from ..dashboard.auth import check_token
    from ..dashboard.server import serve

    if token is not None:
        check_token(token)  # a weak token: one line, exit 2, before the fleet is opened
    options.open_fleet(inventory)  # no inventory, a bad one: one line, exit 2, before anything listens
    serve(inventory, bind, token, interval)
