"""The robot side: its edge bundle (also what `ccrp robot sim` installs)."""

from __future__ import annotations

from pathlib import Path

from .errors import InputError
from .fleet import Fleet, clone_view


def edge_files(fleet: Fleet, robot: str, remote: str | None = None) -> tuple[list, str]:
    """The robot's bundle files and the endpoint its profile dials."""
    from .render import bundles

    state = fleet.store.load_state()
    view = clone_view(fleet, state, robot)
    rec = state.robots.get(robot)
    endpoint = remote or (rec.public_endpoint if rec else None)
    if not endpoint:
        raise InputError(
            f"the public endpoint of clone {view.addr.clone_host} is not known yet",
            hint="create the clone first (`ccrp clone create`), or pass --remote HOST[:PORT]",
        )
    return bundles.edge_bundle(view, fleet.pki.credentials(robot), endpoint), endpoint


def write_edge(fleet: Fleet, robot: str, out: Path, remote: str | None = None) -> Path:
    from .render import bundles

    files, endpoint = edge_files(fleet, robot, remote)
    return bundles.write_bundle(out, files, {"fleet": fleet.name, "robot": robot, "kind": "edge", "remote": endpoint})
