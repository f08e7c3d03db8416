"""The camera view as a clone service (docs/architecture.md, "The camera view"): what it keeps on a
clone. `fleet up` pushes the camera agent (agent/camera.py) with the clone's other files, checked
by digest, so a clone holds this ccrp's copy before anyone asks it for a frame; nothing comes with
the user-data (every clone's would grow for an agent most never run) and nothing starts: the agent
runs only while it is used, started as a transient unit of the `ros` user by the first read and
ending by itself after CAMERA_IDLE_S without one. Reading frames and starting the agent is the
operator's side, `ccrp robot camera` and the dashboard's camera view (robot/camera.py), which
pushes the agent itself only to a clone that does not hold this copy (one made before the service,
or not brought up since ccrp changed). No status field: nothing on the clone reports the view, and
whether the agent runs is what each read finds out."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..models.layout import CCRP_LIB
from ..render.files import BundleFile
from .base import CloneService, ServiceContext

if TYPE_CHECKING:
    from ..providers.base import Reaches

AGENT = f"{CCRP_LIB}/camera.py"
UNIT = "ccrp-camera"
SOCKET = "/run/ccrp-camera/camera.sock"
CAMERA_IDLE_S = 120
# The agent's unit: the clone's ROS environment, the `ros` user, logs and socket in memory.
UNIT_OPTIONS = ["--description", "ccrp camera agent (ccrp robot camera, the dashboard's camera view)",
                "--property", "User=ros", "--property", "RuntimeDirectory=ccrp-camera",
                "--property", "RuntimeDirectoryMode=0700", "--property", "NoNewPrivileges=yes",
                "--property", "ProtectSystem=full", "--property", "ProtectHome=yes", "--property", "PrivateTmp=yes",
                "--setenv", "HOME=/run/ccrp-camera", "--setenv", "ROS_HOME=/run/ccrp-camera",
                "--setenv", "ROS_LOG_DIR=/run/ccrp-camera/log"]


def agent_file() -> BundleFile:
    """The camera agent as this ccrp ships it, where its unit runs it from."""
    from ..resources import agent_source

    return BundleFile("camera.py", agent_source("camera"), 0o644, AGENT)


class Camera(CloneService):
    """Every clone holds the agent (any robot may have a camera); `fleet up` pushes it once the
    clone serves when the clone's copy is missing or another, and starts nothing. It is not among a
    snapshot's agents (Boot.image_agents), which would spare that one push per new clone: a bake's
    builder user-data would carry it too, and on AWS that took 12.9 of the 16 KiB gzipped to 14.7."""

    name = "camera"

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        return [agent_file()]

    def apply(self, clone: Reaches, robot: str, files: list[BundleFile], have: dict[str, str],
              pushed_keys: bool) -> list[str]:
        from ..probe import same

        # An agent running the older copy keeps it until it ends (CAMERA_IDLE_S after its last
        # read): stopping it would blank a view that is open; the next start runs this one.
        if files and not same(have, files):
            clone.transport.push_files(robot, files, restart=[])
        return []
