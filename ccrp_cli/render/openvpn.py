"""OpenVPN server config (clone), its per-robot ccd entry, and the robot's inline profile."""

from __future__ import annotations

from ..errors import InputError
from ..models.values import parse_endpoint
from ..pki.store import RobotCredentials
from ..templates import render
from .view import CloneView

ROBOT_CREDENTIALS_PATH = "/etc/ccrp/vpn-credentials"
DEVICE_CREDENTIALS_PATH = "/etc/ccrp/power-credentials"


def server_conf(view: CloneView, user: str = "openvpn", group: str = "openvpn") -> str:
    return render("openvpn/server.conf.j2", **view.ctx(user=user, group=group))


def ccd_entry(view: CloneView) -> str:
    a = view.addr
    return f"ifconfig-push {a.robot_vpn_ip} {a.vpn_subnet.netmask}\n"


def device_ccd_entry(view: CloneView) -> str:
    """The power device's: its own fixed address, which the clone's firewall lets reach only the
    power agent."""
    a = view.addr
    return f"ifconfig-push {a.device_vpn_ip} {a.vpn_subnet.netmask}\n"


def client_profile(
    view: CloneView,
    creds: RobotCredentials,
    remote: str,
    credentials_path: str = ROBOT_CREDENTIALS_PATH,
    device: bool = False,
) -> str:
    """The robot's profile, or with `device` its power device's (its own certificate, key and
    credentials file, its own tun device); `remote` is HOST[:PORT] or [IPV6]:PORT, checked here
    because the line `remote HOST PORT` is a directive of a file root runs on the robot."""
    try:
        endpoint = parse_endpoint(remote, view.inv.vpn.port)
    except ValueError as exc:
        raise InputError(f"remote endpoint: {exc}") from None
    return render(
        "openvpn/client.ovpn.j2",
        **view.ctx(
            creds=creds,
            remote_host=endpoint.host,  # OpenVPN takes an IPv6 address bare, without brackets
            remote_port=endpoint.port,
            credentials_path=DEVICE_CREDENTIALS_PATH if device else credentials_path,
            who=f"the power device of robot {view.name}" if device else f"robot {view.name}",
            dev="ccrppwr" if device else "ccrpvpn",
            cert_pem=creds.power_cert_pem if device else creds.client_cert_pem,
            key_pem=creds.power_key_pem if device else creds.client_key_pem,
        ),
    )
