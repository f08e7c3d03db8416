"""Bundles written to a directory: the clone's secrets (pushed after boot) and the robot's edge
bundle (installed on the robot). Each carries a manifest.json naming every file and its mode."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ..models.names import power_name
from ..pki.store import RobotCredentials
from ..store import atomic_write, ensure_dir
from . import network, openvpn
from ..templates import render, static
from ..models.layout import RELAY_USER, SECRETS_DIR
from .files import BundleFile
from .view import CloneView


def clone_secrets(view: CloneView, creds: RobotCredentials) -> list[BundleFile]:
    """What the clone needs but user-data must never carry."""
    return [
        BundleFile("ca.crt", creds.ca_pem, 0o644, f"{SECRETS_DIR}/ca.crt"),
        crl_file(creds.crl_pem),
        BundleFile("server.crt", creds.server_cert_pem, 0o644, f"{SECRETS_DIR}/server.crt"),
        BundleFile("server.key", creds.server_key_pem, 0o600, f"{SECRETS_DIR}/server.key"),
        BundleFile("tc.key", creds.tls_crypt_key, 0o600, f"{SECRETS_DIR}/tc.key"),
        passwd_file(view, creds),
    ] + relay_secrets(view, creds)


def passwd_file(view: CloneView, creds: RobotCredentials) -> BundleFile:
    """Who may connect to the clone, with their password hashes: the robot, and its power device
    once it has one. Read by ccrp-auth after OpenVPN dropped to the openvpn user, at every
    handshake: a new line needs no restart."""
    lines = f"{view.name}:{creds.password_hash}\n"
    if creds.power_password_hash:
        lines += f"{power_name(view.name)}:{creds.power_password_hash}\n"
    return BundleFile("passwd", lines, 0o640, f"{SECRETS_DIR}/passwd", "openvpn")


def crl_file(pem: str) -> BundleFile:
    """The CRL as pushed to a clone: OpenVPN re-reads it when it changes, no restart needed."""
    return BundleFile("crl.pem", pem, 0o644, f"{SECRETS_DIR}/crl.pem")


def relay_secrets(view: CloneView, creds: RobotCredentials) -> list[BundleFile]:
    """The relay's mutual-TLS certificate and key, and the relay CA that peers' certificates must
    chain to (not the VPN's CA: robots' certificates come from that one)."""
    if not creds.relay_cert_pem or not creds.relay_key_pem or not creds.relay_ca_pem:
        return []
    return [
        BundleFile("relay-ca.crt", creds.relay_ca_pem, 0o644, f"{SECRETS_DIR}/relay-ca.crt"),
        BundleFile("relay.crt", creds.relay_cert_pem, 0o644, f"{SECRETS_DIR}/relay.crt"),
        BundleFile("relay.key", creds.relay_key_pem, 0o640, f"{SECRETS_DIR}/relay.key", RELAY_USER),
    ]


def edge_bundle(view: CloneView, creds: RobotCredentials, remote: str) -> list[BundleFile]:
    a = view.addr
    if view.inv.ros.ros2:
        # No master to reach: the watchdog pings the clone's VPN address, the robot's DDS peer.
        check = f"CCRP_CLONE_HOST={a.clone_vpn_ip}\nCCRP_WATCHDOG_CHECK=icmp\n"
    else:
        check = f"CCRP_CLONE_HOST={a.clone_host}\nCCRP_MASTER_PORT={view.inv.ros.master_port}\n"
    watchdog_env = check + "CCRP_WATCHDOG_INTERVAL=2\nCCRP_WATCHDOG_FAIL_AFTER=2\n"
    return [
        BundleFile("robot.ovpn", openvpn.client_profile(view, creds, remote), 0o600),
        BundleFile("vpn-credentials", f"{view.name}\n{creds.password}\n", 0o600),
        BundleFile("ros.env", network.ros_env(view, "robot"), 0o644),
        BundleFile("ccrp-ros.sh", static("edge/ccrp-ros.sh"), 0o644),
        BundleFile("hosts", network.hosts_block(view, "robot"), 0o644),
        BundleFile("chrony.conf", network.chrony_conf(view, "robot"), 0o644),
        BundleFile("watchdog.env", watchdog_env, 0o644),
        BundleFile("ccrp-watchdog", static("edge/ccrp-watchdog"), 0o755),
        BundleFile("ccrp-vpn.service", static("edge/ccrp-vpn.service"), 0o644),
        BundleFile("ccrp-watchdog.service", static("edge/ccrp-watchdog.service"), 0o644),
        BundleFile("install.sh", render("edge/install.sh.j2", **view.ctx()), 0o755),
    ] + (ros2_edge(view) if view.inv.ros.ros2 else [])


def power_bundle(view: CloneView, creds: RobotCredentials, remote: str) -> list[BundleFile]:
    """What the robot's power device installs: its own VPN client of the robot's clone (its
    certificate, key and password) and the agent that reports to the clone's power agent and sets
    the relay (docs/dashboard.md, Robot power)."""
    from ..models.layout import POWER_PORT

    a = view.addr
    env = f"CCRP_POWER_CLONE={a.clone_vpn_ip}\nCCRP_POWER_PORT={POWER_PORT}\n"
    return [
        BundleFile("power.ovpn", openvpn.client_profile(view, creds, remote, device=True), 0o600),
        BundleFile("power-credentials", f"{power_name(view.name)}\n{creds.power_password}\n", 0o600),
        BundleFile("power.env", env, 0o644),
        BundleFile("ccrp-power-device", static("edge/ccrp-power-device"), 0o755),
        BundleFile("ccrp-power-vpn.service", static("edge/ccrp-power-vpn.service"), 0o644),
        BundleFile("ccrp-power-device.service", static("edge/ccrp-power-device.service"), 0o644),
        BundleFile("install.sh", render("edge/install-power.sh.j2", **view.ctx()), 0o755),
    ]


def ros2_edge(view: CloneView) -> list[BundleFile]:
    """A ROS 2 robot's firewall for RTPS (its domain's ports only through the tunnel), and the
    Fast DDS profile that has its participants announce the tunnel's end whenever they started."""
    ports = network.rtps_ports(view.addr.index)
    return [BundleFile("ccrp-rtps-guard", render("edge/ccrp-rtps-guard.j2", **view.ctx(ports=ports)), 0o755),
            BundleFile("ccrp-rtps-guard.service", static("edge/ccrp-rtps-guard.service"), 0o644),
            BundleFile("fastdds.xml", render("edge/fastdds.xml.j2", **view.ctx()), 0o644)]


def write_bundle(out: Path, files: list[BundleFile], meta: dict[str, str]) -> Path:
    """Write files (atomically, with their modes) and manifest.json into `out` (made 0700)."""
    ensure_dir(out)
    entries = []
    for f in files:
        atomic_write(out / f.name, f.content, mode=f.mode, durable=False)
        entry = {"name": f.name, "mode": f"{f.mode:04o}", "sha256": hashlib.sha256(f.content.encode()).hexdigest()}
        if f.dest:
            entry.update(dest=f.dest, group=f.group)
        entries.append(entry)
    atomic_write(out / "manifest.json", json.dumps({**meta, "files": entries}, indent=2) + "\n", mode=0o644, durable=False)
    return out
