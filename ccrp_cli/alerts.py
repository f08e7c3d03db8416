"""Alerts of a fleet, from its status rows and its PKI: what `ccrp status` lists under its table
and the dashboard shows (docs/dashboard.md). Each is {level, kind, robot, text}: a sentence made
from status fields, CNs and dates, never a secret.
"""

from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING, Any

from .models.status import StatusRow

if TYPE_CHECKING:
    from .fleet import Fleet

# A certificate or the CRL this close to its end is an alert (as `ccrp vpn list` warns of the CRL);
# under ERROR_DAYS it is an error.
WARN_DAYS = 30
ERROR_DAYS = 7


def _alert(level: str, kind: str, robot: str | None, text: str) -> dict:
    return {"level": level, "kind": kind, "robot": robot, "text": text}


def row_alerts(row: StatusRow) -> list[dict]:
    """Alerts of one robot from its status row: clone down, robot disconnected, relay peer down,
    robot brainless (its watchdog lost the clone: most often because the clone is down)."""
    alerts = clone_alerts(row)
    robot, p, w = row.robot, row.power, row.watchdog
    if p is not None and p.robot == "off":  # switched off on purpose: not a disconnection to warn of
        alerts = [a for a in alerts if a["kind"] != "robot-disconnected"]
        alerts.append(_alert("info", "robot-powered-off", robot,
                             f"{robot} is powered off (its power device reported it at {(p.reported_at or '')[11:19]} UTC)"))
    if p is not None and p.silent:
        alerts.append(_alert("warning", "power-device-silent", robot,
                             f"the power device of {robot} has not reported for {p.age_s or 0:.0f} s (it reports every 3 s)"))
    if w is not None and w.state == "brainless":
        since = f" since {w.since[11:19]} UTC" if w.since else ""
        motors = f" (motors {w.motors})" if w.motors else ""
        alerts.append(_alert("error", "robot-brainless", robot,
                             f"{robot} is brainless{since}: its watchdog lost the clone and ran its fallback{motors}"))
    return alerts


# Restarts after which a node counts as in a restart loop (its unit restarts every 3 s).
RESTART_LOOP = 3


def clone_alerts(row: StatusRow) -> list[dict]:
    robot, status = row.robot, row.status
    if status == "stopped (idle)":
        return [_alert("info", "clone-stopped-idle", robot,
                       f"clone of {robot} stopped itself: its robot stayed away (start it to bring it back)")]
    if status == "absent":
        if row.revoked_at:
            return [_alert("info", "robot-revoked", robot, f"{robot} is revoked since {row.revoked_at[:10]}")]
        if row.phase == "planned":
            return [_alert("info", "clone-absent", robot, f"{robot} has no clone yet (fleet up creates it)")]
        return [_alert("error", "clone-down", robot, f"clone of {robot} is gone (fleet up creates it again)")]
    if row.unreachable:
        return [_alert("error", "clone-unreachable", robot,
                       f"clone of {robot} is listed {status.split(' (')[0]} but does not answer (booting, or shutting down)")]
    # ccrp's word for the clone, the same on every provider: OpenStack's running clone is ACTIVE, GCP's
    # RUNNING (the real AIO cloud showed "clone of r1 is down (ACTIVE)" while it served).
    if row.state != "running":
        return [_alert("error", "clone-down", robot, f"clone of {robot} is down ({status})")]
    alerts = []
    if row.secrets is False:
        alerts.append(_alert("error", "clone-keys-gone", robot, f"clone of {robot} lost its keys (fleet up pushes them)"))
    if not row.master_reachable:
        what = "ROS master" if row.ros_distro == "noetic" else "ROS 2 graph"  # docs/ros2.md
        alerts.append(_alert("error", "master-down", robot, f"{what} of {robot}'s clone does not answer"))
    if row.revoked_at:
        if row.vpn_connected:
            alerts.append(_alert("error", "revoked-connected", robot,
                                 f"{robot} is revoked but still connected (run vpn revoke again if it stays)"))
        else:
            alerts.append(_alert("info", "robot-revoked", robot, f"{robot} is revoked since {row.revoked_at[:10]}"))
    elif not row.vpn_connected:
        extra = f"; stale nodes on its master: {', '.join(row.stale_nodes)}" if row.stale_nodes else ""
        alerts.append(_alert("warning", "robot-disconnected", robot, f"{robot} is not connected to its clone{extra}"))
    for node in row.nodes or []:  # the robot's own software (docs/workloads.md)
        # auto-restart: it ended and systemd waits to start it again, which is what a node whose
        # program is missing does every 3 s (`fleet up` and deploy fail such a node at once too).
        if node.state == "failed" or node.sub == "auto-restart" or (node.restarts or 0) >= RESTART_LOOP:
            alerts.append(_alert("error", "node-failing", robot,
                                 f"node {node.name} on {robot}'s clone is {node.state} after {node.restarts or 0} "
                                 f"restart(s): ccrp logs --robot {robot} {node.name}"))
    peers = row.relay_peers
    if peers and not row.relay_running:
        alerts.append(_alert("error", "relay-down", robot, f"relay of {robot}'s clone is not running: nothing is shared"))
    else:
        down = sorted(p for p, up in peers.items() if not up)
        if down:
            alerts.append(_alert("warning", "relay-peer-down", robot,
                                 f"relay peer(s) of {robot} down: {', '.join(down)}"))
    return alerts


def pki_alerts(pki, robots: list[str], now: dt.datetime | None = None) -> list[dict]:
    """Certificates (the current one of each CN: the CAs and the certificates of `robots`) and the
    CRL that end within WARN_DAYS, or have ended. Reads the index and the CRL's date, no key."""
    if not pki.exists():
        return []
    real_now = dt.datetime.now(dt.timezone.utc)
    now = now or real_now
    alerts = []

    def left(until: dt.datetime) -> float:
        return (until - now).total_seconds() / 86400

    def level(days: float) -> str:
        return "error" if days < ERROR_DAYS else "warning"

    crl_days = pki.crl_days_left() - (now - real_now).total_seconds() / 86400  # as of `now`
    if crl_days < WARN_DAYS:
        text = ("the fleet's CRL has expired: every robot is refused (ccrp vpn init re-issues it)" if crl_days < 0
                else f"the fleet's CRL expires in {crl_days:.0f} days (ccrp vpn init re-issues it)")
        alerts.append(_alert(level(crl_days), "crl-expiry", None, text))
    index = pki.load_index()
    wanted = set(robots)
    newest: dict[str, Any] = {}
    for rec in index.certs:  # in issue order: the last unrevoked one of a CN is its current one
        if not rec.revoked and (rec.robot is None or rec.robot in wanted):
            newest[rec.cn] = rec
    for cn, rec in sorted(newest.items()):
        days = left(rec.not_after)
        if days >= WARN_DAYS:
            continue
        what = f"{rec.profile} certificate {cn}"
        fix = "ccrp vpn issue-cert --robot " + rec.robot + " --renew" if rec.robot else "a new CA"
        text = f"{what} has expired ({fix})" if days < 0 else f"{what} expires in {days:.0f} days ({fix})"
        alerts.append(_alert(level(days), "cert-expiry", rec.robot, text))
    return alerts




LEVELS = {"error": 0, "warning": 1, "info": 2}


def fleet_alerts(fleet: Fleet, rows: list[StatusRow]) -> list[dict]:
    """Every alert of the fleet, from its status rows and its PKI, most serious first."""
    alerts = [a for row in rows for a in row_alerts(row)]
    alerts += pki_alerts(fleet.pki, [r.robot for r in rows])
    return sorted(alerts, key=lambda a: LEVELS[a["level"]])
