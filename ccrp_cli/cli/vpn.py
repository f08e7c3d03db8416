"""ccrp vpn ...: the fleet's CA, certificates, CRL."""

from __future__ import annotations

import enum
from typing import TYPE_CHECKING, Annotated

import typer

from . import options, output

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Provider

app = typer.Typer(help="Fleet PKI: CA, robot and clone certificates, revocation.", no_args_is_help=True, rich_markup_mode=None)

def _ops():
    from ..ops import vpn

    return vpn


class CertKind(str, enum.Enum):
    client = "client"
    server = "server"
    relay = "relay"
    power = "power"
    all = "all"


def _provider(fleet: Fleet) -> Provider:
    from ..providers import get_provider

    return get_provider(fleet.inventory)


CERT_COLUMNS = ["SERIAL", "CN", "PROFILE", "NOT AFTER", "REVOKED", "PATH"]


def _rows(records: list[dict]) -> list[tuple]:
    return [
        (r["serial"][:16], r["cn"], r["profile"], r["not_after"][:10], "yes" if r["revoked"] else "", r["path"])
        for r in records
    ]


@app.command()
def init(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """Create the fleet's CA and CRL (idempotent)."""
    result = _ops().init(options.open_fleet(inventory))
    if as_json:
        output.emit_json(result)
    else:
        verb = "created" if result["created"] else "already exists:"
        output.info(f"fleet {result['fleet']!r} CA {verb} {result['ca']} (CRL {result['crl']})")


@app.command("issue-cert")
def issue_cert(
    inventory: options.Inventory,
    robot: options.Robot,
    renew: Annotated[bool, typer.Option(
        help="Replace valid certificates: the old ones are revoked, password and tls-crypt key rotated, "
             "and a running clone takes the new set at once.")] = False,
    as_json: options.Json = False,
) -> None:
    """Issue the robot's client certificate and its clone's server certificate.

    Also the one way back in for a revoked robot (with a new password and tls-crypt key)."""
    from ..ops.vpn import vpn_issue

    records = vpn_issue(options.open_fleet(inventory), robot, renew, output.info)
    if not as_json:
        for r in records:
            output.info(f"{'issued' if r['issued'] else 'kept valid'} {r['profile']} certificate {r['cn']} ({r['path']})")
    output.emit(records, as_json, CERT_COLUMNS, _rows(records))


@app.command()
def revoke(
    inventory: options.Inventory,
    robot: options.Robot,
    cert: Annotated[CertKind, typer.Option(
        help="Which certificates: the robot's own and its power device's (client, default: it stays out until "
             "`vpn issue-cert`), its power device's alone (power), its clone's VPN server, its clone's relay, or all.")] = CertKind.client,
    as_json: options.Json = False,
) -> None:
    """Revoke the robot's certificates: its live session ends and every running clone gets the CRL."""
    from ..ops.vpn import vpn_revoke

    fleet = options.open_fleet(inventory)
    records = vpn_revoke(fleet, _provider(fleet), robot, output.info, cert.value)
    if not as_json:
        output.info(f"revoked {len(records)} certificate(s) of robot {robot!r}; CRL re-issued")
    output.emit(records, as_json, CERT_COLUMNS, _rows(records))


@app.command("list")
def list_(inventory: options.Inventory, as_json: options.Json = False) -> None:
    """List the fleet's certificates: serial, CN, not-after, revoked, file path."""
    fleet = options.open_fleet(inventory)
    records = _ops().list_certs(fleet)
    warning = _ops().crl_warning(fleet)
    if warning:
        output.warn(warning)
    output.emit(records, as_json, CERT_COLUMNS, _rows(records))
