"""The API manager, a platform service on the clone (docs/services.md): what `fleet up` pushes for
it, and how `ccrp status` reports it. It is agent/api_manager.py as ccrp-api-manager.service,
its setting a pushed file (/etc/ccrp/api_manager.json, like relay.json), its backend's key (if any)
pushed into the clone's secrets, never into user-data."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import CcrpError, shown
from ..models.inventory import Inventory, Robot
from ..render.files import BundleFile
from ..models.layout import API_USER, CCRP_ETC, SECRETS_DIR
from .base import Boot, CloneService, ServiceContext

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..models.state import FleetState
    from ..providers.base import Reaches

API_UNIT = "ccrp-api-manager.service"
API_CONFIG = f"{CCRP_ETC}/api_manager.json"
AGENT_DIR = "/usr/local/lib/ccrp"  # where the Noetic snapshot has the agent, and fleet up pushes a ROS 2 one
API_STATUS = "/run/ccrp-api-manager/status.json"  # agent/health.py has its own copy
GOOGLE_KEY = f"{SECRETS_DIR}/google-vision.json"
# Retries of a failed backend call (agent/api_manager.py Caller): attempts per frame, then backoff
# base and cap in seconds.
RETRY = {"attempts": 3, "base": 0.5, "max": 30.0}


def api_manager_config(inv: Inventory, robot: Robot) -> dict | None:
    """The agent's config for robot's clone, or None when its clone runs no API manager."""
    s = inv.api_manager_of(robot)
    if s is None:
        return None
    google = s.google_vision
    return {
        "robot": robot.name, "input": s.input, "output": s.output, "backend": s.backend, "rate": s.rate,
        "min_confidence": s.min_confidence, "options": dict(s.options), "retry": RETRY, "status": API_STATUS,
        "google_vision": {"endpoint": google.endpoint, "timeout": google.timeout,
                          "credentials": GOOGLE_KEY if google.credentials else None},
    }


def google_key(path: str) -> str:
    """The service-account key file named by the inventory, checked to be one (read on the
    operator's machine at `fleet up`)."""
    p = Path(path).expanduser()
    try:
        text = p.read_text()
        data = json.loads(text)
    except (OSError, ValueError) as exc:
        raise CcrpError(f"google_vision.credentials {shown(str(p))}: {type(exc).__name__}: {shown(str(exc))}",
                        hint="a service-account key file (JSON) from the Google Cloud console") from None
    if not isinstance(data, dict) or data.get("type") != "service_account" or "private_key" not in data:
        raise CcrpError(f"google_vision.credentials {shown(str(p))} is not a service-account key file")
    return text


def api_manager_files(inv: Inventory, robot: Robot) -> list[BundleFile]:
    """What `fleet up` pushes for robot's API manager: its config, its Vision key when it has one,
    and the agent (api_manager.py, and its rclpy side on ROS 2), as the knowledge agent is pushed:
    a bare cloud clone's user-data carries only the relay (Boot.bare_agents), since with the API
    manager too a Noetic one went over AWS's 16 KiB gzipped. A snapshot's copy (Boot.image_agents)
    is the same file, so it is not sent again. [] when the clone runs none."""
    from ..resources import agent_source

    cfg = api_manager_config(inv, robot)
    if cfg is None:
        return []
    files = [BundleFile("api_manager.json", json.dumps(cfg, indent=1, sort_keys=True) + "\n", 0o644, API_CONFIG)]
    names = ("api_manager", "api_manager_ros2") if inv.ros.ros2 else ("api_manager",)
    files += [BundleFile(f"{name}.py", agent_source(name), 0o644, f"{AGENT_DIR}/{name}.py") for name in names]
    key = key_path(inv, robot)
    if key:
        files.append(BundleFile("google-vision.json", google_key(key), 0o640, GOOGLE_KEY, API_USER))
    return files


def key_path(inv: Inventory, robot: Robot) -> str | None:
    """The Vision key file the robot's API manager is given, if any."""
    setting = inv.api_manager_of(robot)
    if setting is not None and setting.backend == "google-vision":
        return setting.google_vision.credentials or None
    return None


def absent_config() -> BundleFile:
    """Probed on a clone whose robot runs no API manager: if the file is there, it is removed."""
    return BundleFile("api_manager.json", "", 0o644, API_CONFIG)


# Whether a clone can run the service: its unit and its user (user-data); the agent comes with the
# config (api_manager_files).
HAS_UNIT_SH = f"test -e /etc/systemd/system/{API_UNIT} && getent passwd {API_USER} >/dev/null"
# Turns the service off on a clone: its config and key gone, the unit stopped.
OFF_SH = f'rm -f "{API_CONFIG}" "{GOOGLE_KEY}" && systemctl stop {API_UNIT}'


def apply_api_manager(provider: Reaches, robot: str, files: list[BundleFile], have: dict[str, str]) -> None:
    """Bring robot's clone in line with `files` (api_manager_files), given the digests of what it
    holds: push and restart the agent when they differ, or turn the service off."""
    from ..probe import same

    if files:
        if not same(have, files):
            rc, _ = provider.transport.exec(robot, ["sh", "-c", HAS_UNIT_SH], timeout=30)
            if rc != 0:
                raise CcrpError(
                    f"robot {robot!r}'s clone has no API manager: it was made from an older snapshot or user-data",
                    hint=f"ccrp snapshot build -i INVENTORY, then ccrp clone delete -i INVENTORY --robot {robot} "
                         f"and ccrp fleet up -i INVENTORY")
            provider.transport.push_files(robot, files, restart=[API_UNIT])
    elif API_CONFIG in have:
        rc, out = provider.transport.exec(robot, ["sh", "-c", OFF_SH], timeout=30)
        if rc != 0:
            raise CcrpError(f"cannot turn the API manager off on robot {robot!r}'s clone: {out.strip()[-200:]}")


def api_manager_row(inv: Inventory, robot: Robot, health: dict | None) -> dict | None:
    """`ccrp status`'s view of robot's API manager: None when it has none; `running` only while
    the agent reports (a status file under 10 s old, agent/health.py)."""
    s = inv.api_manager_of(robot)
    if s is None:
        return None
    h = (health or {}).get("api_manager") or {}
    return {"running": bool(h.get("running")), "backend": s.backend, "calls": h.get("calls", 0),
            "errors": h.get("errors", 0), "published": h.get("published", 0),
            "last_latency_ms": h.get("last_latency_ms"), "last_error": h.get("last_error")}


class ApiManager(CloneService):
    """Its unit is in every clone's user-data and starts only with its config; `fleet up` pushes the
    config, the agent and the backend's key once the clone serves, and restarts it."""

    name = "api_manager"
    # The agent in every ROS 1 snapshot with its packages; pushed by fleet up where it is not.
    boot = Boot(units=(API_UNIT,), image_agents=("api_manager",), users=(API_USER,))

    def check(self, fleet: Fleet, robot: Robot) -> None:
        key = key_path(fleet.inventory, robot)
        if key:
            google_key(key)  # a key file that is not one is refused before the clone is made

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        return api_manager_files(ctx.fleet.inventory, ctx.robot)

    def absent(self) -> list[BundleFile]:
        return [absent_config()]

    def apply(self, clone: Reaches, robot: str, files: list[BundleFile], have: dict[str, str],
              pushed_keys: bool) -> list[str]:
        apply_api_manager(clone, robot, files, have)
        return []

    def status(self, fleet: Fleet, state: FleetState, robot: Robot, health: dict | None) -> dict:
        return {"api_manager": api_manager_row(fleet.inventory, robot, health)}
