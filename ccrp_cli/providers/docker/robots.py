"""Simulated robots on the Docker backend: a container on <fleet>-public only that installs the
robot's edge bundle exactly as a real robot would, then runs a demo ROS node."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import owner_labels
from .archive import tar_files
from .provider import DockerProvider

BUNDLE_DIR = "opt/ccrp-bundle"


def start(provider: DockerProvider, robot: str, image: str, bundle: list, demo_node: str) -> str:
    """(Re)create the simulated robot and install `bundle` in it. Returns the container id."""
    stop(provider, robot)
    c = provider.client.containers.create(
        image,
        name=provider.container_name(robot, role="robot-sim"),
        hostname=robot,
        labels=owner_labels(provider.fleet, "robot-sim", robot),
        detach=True,
        network=provider.public_net,  # never the common network: robots reach only their clone
        cap_add=["NET_ADMIN", "SYS_ADMIN"],
        devices=["/dev/net/tun:/dev/net/tun:rwm"],
        tmpfs={"/run": "", "/run/lock": "", "/tmp": ""},
        volumes={"/sys/fs/cgroup": {"bind": "/sys/fs/cgroup", "mode": "ro"}},
        security_opt=["seccomp=unconfined"],
        stop_signal="SIGRTMIN+3",
    )
    files = [(f"{BUNDLE_DIR}/{f.name}", f.content.encode(), f.mode) for f in bundle]
    files += [
        ("etc/cloud/cloud-init.disabled", b"a robot, not a clone\n", 0o644),
        ("usr/local/lib/ccrp/ccrp-demo-node", demo_node.encode(), 0o755),
    ]
    c.put_archive("/", tar_files(files, make_dirs=True))
    c.start()
    provider.wait_systemd(robot, role="robot-sim")  # install.sh enables units
    rc, out = provider.exec(robot, [f"/{BUNDLE_DIR}/install.sh"], timeout=60, role="robot-sim")
    if rc != 0:
        raise CcrpError(f"install.sh failed on simulated robot {robot}: {out.strip()[-300:]}")
    rc, out = provider.exec(
        robot,
        ["systemd-run", "--unit", "ccrp-demo-node", "--property", "EnvironmentFile=/etc/ccrp/ros.env",
         "--property", "Restart=always", "--property", "RestartSec=2",
         "/usr/bin/python3", "/usr/local/lib/ccrp/ccrp-demo-node"],
        role="robot-sim",
    )
    if rc != 0:
        raise CcrpError(f"cannot start the demo node on simulated robot {robot}: {out.strip()[-200:]}")
    return c.id[:12]


def stop(provider: DockerProvider, robot: str) -> bool:
    c = provider._container(robot, role="robot-sim")
    if c is None:
        return False
    c.remove(force=True, v=True)
    return True


def vpn_state(provider: DockerProvider, robot: str) -> dict:
    """The simulated robot's view: tunnel address and watchdog state."""
    c = provider._container(robot, role="robot-sim")
    if c is None or c.status != "running":
        return {"running": False}
    _, addr = provider.exec(robot, ["ip", "-4", "-o", "addr", "show", "dev", "ccrpvpn"], role="robot-sim")
    _, wd = provider.exec(robot, ["cat", "/run/ccrp/clone-state"], role="robot-sim")
    ip = addr.split()[3].split("/")[0] if "inet" in addr else None
    return {"running": True, "vpn_ip": ip, "watchdog": wd.strip() if "No such" not in wd else None}
