"""The robot side: its edge bundle (also what `ccrp robot sim` installs)."""

from __future__ import annotations

from pathlib import Path

from ..errors import InputError, cannot_write
from ..fleet import Fleet, clone_view
from ..models.values import parse_endpoint


def edge_files(fleet: Fleet, robot: str, remote: str | None = None) -> tuple[list, str]:
    """The robot's bundle files and the endpoint its profile dials."""
    from ..render import bundles

    state = fleet.store.load_state()
    view = clone_view(fleet, state, robot)
    endpoint = endpoint_of(fleet, state, robot, remote)
    return bundles.edge_bundle(view, fleet.pki.credentials(robot), endpoint), endpoint


def endpoint_of(fleet: Fleet, state, robot: str, remote: str | None = None) -> str:
    """HOST:PORT that the robot (or its power device) dials: `remote`, else its clone's endpoint."""
    rec = state.robots.get(robot)
    endpoint = remote or (rec.public_endpoint if rec else None)
    if not endpoint:
        raise InputError(
            f"the public endpoint of the clone of {robot!r} is not known yet",
            hint="create the clone first (`ccrp clone create`), or pass --remote HOST[:PORT]",
        )
    # Parsed here so a bad --remote is refused before anything is written (client_profile parses
    # again: every caller of the renderer gets the same check).
    try:
        return str(parse_endpoint(endpoint, fleet.inventory.vpn.port))
    except ValueError as exc:
        raise InputError(f"remote endpoint: {exc}", hint="HOST, HOST:PORT, IPV6 or [IPV6]:PORT") from None


def write_edge(fleet: Fleet, robot: str, out: Path, remote: str | None = None) -> Path:
    from ..render import bundles

    files, endpoint = edge_files(fleet, robot, remote)
    with cannot_write(out):
        return bundles.write_bundle(out, files, {"fleet": fleet.name, "robot": robot, "kind": "edge", "remote": endpoint})
