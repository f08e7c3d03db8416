"""OpenVPN server config (clone), its per-robot ccd entry, and the robot's inline profile."""

from __future__ import annotations

from ..pki.store import RobotCredentials
from .templates import render
from .view import CloneView

ROBOT_CREDENTIALS_PATH = "/etc/ccrp/vpn-credentials"


def server_conf(view: CloneView, user: str = "openvpn", group: str = "openvpn") -> str:
    return render("openvpn/server.conf.j2", **view.ctx(user=user, group=group))


def ccd_entry(view: CloneView) -> str:
    a = view.addr
    return f"ifconfig-push {a.robot_vpn_ip} {a.vpn_subnet.netmask}\n"


def client_profile(
    view: CloneView,
    creds: RobotCredentials,
    remote: str,
    credentials_path: str = ROBOT_CREDENTIALS_PATH,
) -> str:
    host, _, port = remote.rpartition(":") if ":" in remote else (remote, "", "")
    return render(
        "openvpn/client.ovpn.j2",
        **view.ctx(
            creds=creds,
            remote_host=host,
            remote_port=port or view.inv.vpn.port,
            credentials_path=credentials_path,
        ),
    )
