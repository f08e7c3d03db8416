"""Robot power as a clone service (docs/architecture.md, "Robot power"): the clone's end of the line to
the robot's power device. Everything it needs on the clone comes with the user-data, so `fleet up`
pushes nothing for it: the power agent (agent/power.py, ccrp-power.service), the port systemd holds
for it (ccrp-power.socket), its config and the device's OpenVPN entry (CN <robot>.power, its fixed
address). Its status field is the device's last report, from the clone's health. The operator's
side, `ccrp robot power` and the device's bundle, is robot/power.py."""

from __future__ import annotations

import datetime as dt
import json
import time
from typing import TYPE_CHECKING

from ..fleet import Fleet
from ..models.layout import CCRP_ETC, POWER_PORT, POWER_USER, VPN_DIR
from ..models.inventory import Robot
from ..models.names import power_name
from ..models.state import FleetState
from ..render.files import BundleFile
from .base import Boot, CloneService

if TYPE_CHECKING:
    from ..render.view import CloneView

SOCKET = "ccrp-power.socket"
REPORT_S = 3.0  # the device reports every 3 s; three missed reports make it silent
SILENT_S = 3 * REPORT_S


def parse_report(text: str, now: float | None = None) -> dict | None:
    """A report as the clone keeps it (one JSON line) -> {"relay", "robot", "reported_at", "age_s",
    "silent"}; the time is the clone's, when the report arrived."""
    try:
        data = json.loads(text)
        t = float(data["t"])
        relay, robot = data["relay"], data["robot"]
    except (ValueError, KeyError, TypeError):
        return None
    if relay not in ("on", "off") or robot not in ("running", "off", "starting"):
        return None
    now = time.time() if now is None else now
    age = round(max(0.0, now - t), 1)
    return {"relay": relay, "robot": robot, "age_s": age, "silent": age > SILENT_S,
            "reported_at": dt.datetime.fromtimestamp(t, dt.timezone.utc).isoformat(timespec="seconds")}


def boot_files(view: CloneView) -> list[BundleFile]:
    """The device's OpenVPN entry (its own fixed address, which the firewall lets reach only the
    agent) and the agent's config: where it listens, whom it answers."""
    from ..render.openvpn import device_ccd_entry  # render's OpenVPN, only when user-data is made

    a = view.addr
    config = json.dumps({"listen": str(a.clone_vpn_ip), "port": POWER_PORT, "device": str(a.device_vpn_ip)}) + "\n"
    return [BundleFile(power_name(view.name), device_ccd_entry(view), 0o644, f"{VPN_DIR}/ccd/{power_name(view.name)}"),
            BundleFile("power.json", config, 0o644, f"{CCRP_ETC}/power.json")]


class Power(CloneService):
    name = "power"
    boot = Boot(units=("ccrp-power.service",), sockets=(SOCKET,), agents=("power",), users=(POWER_USER,),
                files=boot_files)

    def status(self, fleet: Fleet, state: FleetState, robot: Robot, health: dict | None) -> dict:
        if health is None:
            return {}
        return {"power": parse_report(health.get("power") or "")}  # None: no device reported since the clone booted
