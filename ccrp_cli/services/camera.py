"""The camera view as a clone service (docs/architecture.md, "The camera view"): what it runs on a
clone. Nothing comes with the user-data and `fleet up` pushes nothing: the camera agent
(agent/camera.py) is pushed and started, as a transient unit of the `ros` user, by the first read
(robot/camera.py, the operator's side), and ends by itself after CAMERA_IDLE_S without a read. A
clone that never showed a camera runs none of it."""

from __future__ import annotations

from ..layout import CCRP_LIB
from ..render.files import BundleFile
from ..resources import agent_source
from .base import CloneService

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
    """The agent as the first read pushes it: this ccrp's copy."""
    return BundleFile("camera.py", agent_source("camera"), 0o644, AGENT)


class Camera(CloneService):
    """Declared for the registry's one list of what runs on a clone; its defaults say the rest:
    nothing in user-data, nothing pushed by `fleet up`, no status field."""

    name = "camera"
