"""ccrp init: a first ccrp.yaml in this directory."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from . import options, output


def init(
    # No default written here: the backend says it is init's (its InitSection), and the registry
    # is read only when init runs, not by every `ccrp` start.
    provider: Annotated[str, typer.Option("--provider", show_default=False,
                                          help="docker (clones on this host, the default), libvirt (VMs on this host), openstack, gcp or aws.")] = "",
    robots: Annotated[str, typer.Option("--robots", help="Robot names, comma-separated.")] = "nao1,nao2",
    fleet: Annotated[str, typer.Option("--fleet", help="Fleet name (default: this directory's name, if it is a valid one, else 'lab').")] = "",
    distro: Annotated[str, typer.Option("--distro", help="ROS distro of the fleet: jazzy (ROS 2, the default), kilted (ROS 2) or noetic (ROS 1): one recipe each in snapshots/.")] = "jazzy",
    cloud: Annotated[str | None, typer.Option("--cloud", callback=options.cloud_name, show_default=False,
                                       help="openstack: the clouds.yaml entry; flavor, external network and this host's "
                                            "address are then asked of that cloud.")] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="File to write (never overwritten).")] = Path(options.DEFAULT_INVENTORY),
    as_json: options.Json = False,
) -> None:
    """Write a commented ccrp.yaml that validates, with address pools free on this host (Docker
    networks, routes, and the other fleets in $CCRP_HOME); then `ccrp fleet up` needs no -i."""
    from ..ops.init import default_fleet, write
    from ..recipes import is_ros2

    result = write(out, provider, [r.strip() for r in robots.split(",") if r.strip()], fleet or default_fleet(), distro,
                   cloud or "")
    output.info(f"wrote {out} (fleet {result['fleet']!r} on {result['provider']}, ROS {distro}, robots {', '.join(result['robots'])}); "
                f"next: ccrp fleet validate, then ccrp fleet up")
    if is_ros2(distro):
        # A new fleet is ROS 2; the thesis lab and ROS 1 robots are one flag away.
        output.info("for a ROS 1 fleet (robots running ROS 1 Noetic): ccrp init --distro noetic")
    if as_json:
        output.emit_json(result)
