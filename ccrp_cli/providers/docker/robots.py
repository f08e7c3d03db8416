"""Simulated robots: a container on this host that installs the robot's edge bundle exactly as a
real robot would, then runs a demo ROS node. Where it sits is its fleet's backend's word
(base.RobotAttachment): on a Docker fleet <fleet>-public only; on a libvirt fleet a port of the
NAT bridge; on a cloud fleet it dials its clone's public IP from a Docker network of this host
(default: the engine's `bridge`, NATed like a robot on the internet). RobotContainers is the
base.RobotHost the core reaches them through (providers.robot_host), whatever the fleet's backend."""

from __future__ import annotations

from collections.abc import Sequence

from ...errors import CcrpError
from ...templates import static
from ..base import LABEL_ROBOT, RobotAttachment, owner_labels
from .archive import tar_files
from .client import DockerHost
from .provider import CLONE_CAPS, CLONE_SECURITY_OPT

BUNDLE_DIR = "opt/ccrp-bundle"
# The robot image of cloud fleets: the same recipe as a Docker clone (openvpn, ROS 1), built here once.
SIM_IMAGE = "ccrp/robot-sim:{distro}"


def sim_image(host: DockerHost, distro: str, progress=lambda msg: None) -> str:
    """The local image simulated robots of a cloud fleet run, built from the recipe if missing."""
    from ...recipes import platform
    from . import INFO, images

    # Its Dockerfile is a clone image's (images.dockerfile): a ROS 2 distro's has the ROS 2 venv.
    tag = SIM_IMAGE.format(distro=distro)
    try:
        host.engine.images.get(tag)
        return tag
    except host.NotFound:
        pass
    plat = platform(distro, INFO.platform)
    try:
        host.engine.images.get(images.DEFAULT_BASE)
    except host.NotFound:
        images.build_base_image(host.engine, images.DEFAULT_BASE, sorted(set(images.BASE_PACKAGES + plat.packages)), progress)
    progress(f"building the simulated robots' image {tag} (once)")
    # No agents of the clones': a robot runs none (its own come with its bundle).
    images.build_clone_image(host.engine, tag, images.dockerfile("robot-sim", distro, images.DEFAULT_BASE, plat, agents=()),
                             {"ccrp-managed": "true", "ccrp-role": "robot-image"}, progress,
                             images.build_context(plat, progress, distro, agents=()))
    return tag


# The stand-in power line between a simulated robot and its simulated power device: a volume of
# the robot's container that the device's container mounts too (the relay file, the robot's state).
POWER_DIR = "/var/lib/ccrp/power"
SUPPLY_PATH = "/usr/local/lib/ccrp/ccrp-power-supply"


def _create(provider: DockerHost, robot: str, role: str, image: str, network: str, bundle: Sequence, extra: list,
            attach=None, **options):
    """A systemd container of the robot's (a simulated robot or its power device) on `network`,
    with `bundle` in BUNDLE_DIR and `extra` files, booted and its bundle's install.sh run.
    `attach(pid)`, if given, wires the network of a container on network `none` as soon as it
    runs (a libvirt fleet's robot port), before its VPN first dials."""
    c = provider.engine.containers.create(
        image,
        name=provider.container_name(robot, role=role),
        labels=owner_labels(provider.fleet, role, robot),
        detach=True,
        network=network,  # never the common network: robots reach only their clone
        # The clones' privileges (provider.py): the OpenVPN unit's sandbox needs SYS_ADMIN here too.
        cap_add=CLONE_CAPS,
        devices=["/dev/net/tun:/dev/net/tun:rwm"],
        tmpfs={"/run": "", "/run/lock": "", "/tmp": ""},
        security_opt=CLONE_SECURITY_OPT,
        stop_signal="SIGRTMIN+3",
        **options,
    )
    files = [(f"{BUNDLE_DIR}/{f.name}", f.content.encode(), f.mode) for f in bundle]
    files += [("etc/cloud/cloud-init.disabled", b"a robot, not a clone\n", 0o644), *extra]
    c.put_archive("/", tar_files(files, make_dirs=True))
    c.start()
    if attach is not None:
        c.reload()
        try:
            attach(c.attrs["State"]["Pid"])
        except BaseException:
            c.remove(force=True, v=True)
            raise
    provider.wait_systemd(robot, role=role)  # install.sh enables units
    rc, out = provider.exec(robot, [f"/{BUNDLE_DIR}/install.sh"], timeout=60, role=role)
    if rc != 0:
        raise CcrpError(f"install.sh failed in {c.name}: {out.strip()[-300:]}")
    return c


def start(provider: DockerHost, robot: str, image: str, bundle: Sequence, demo_node: str, network: str,
          python: str = "/usr/bin/python3", attach=None) -> str:
    """(Re)create the simulated robot on `network` and install `bundle` in it, then run `demo_node`
    with `python` (a ROS 2 distro's own, /opt/ros/<distro>/bin/python) and its stand-in power
    supply. Returns the container id."""
    stop(provider, robot)
    c = _create(provider, robot, "robot-sim", image, network, bundle, [
        ("usr/local/lib/ccrp/ccrp-demo-node", demo_node.encode(), 0o755),
        # What the robot does without its clone: stop its (stand-in) motors and note the time.
        ("etc/ccrp/fallback.d/50-sim-motors", static("sim/ccrp-sim-fallback").encode(), 0o755),
        (SUPPLY_PATH.lstrip("/"), static("sim/ccrp-power-supply").encode(), 0o755),
    ], attach=attach, hostname=robot, volumes=["/sys/fs/cgroup:/sys/fs/cgroup:ro", POWER_DIR])  # POWER_DIR: an anonymous volume
    # The power line: not one of the robot's units, so it keeps running while the robot is off.
    rc, out = provider.exec(robot, ["systemd-run", "--unit", "ccrp-power-supply", "--property", "Restart=always",
                                    "--property", "RestartSec=1", "/usr/bin/python3", SUPPLY_PATH], role="robot-sim")
    if rc != 0:
        raise CcrpError(f"cannot start the power supply of simulated robot {robot}: {out.strip()[-200:]}")
    rc, out = provider.exec(
        robot,
        ["systemd-run", "--unit", "ccrp-demo-node", "--property", "EnvironmentFile=/etc/ccrp/ros.env",
         "--property", "Restart=always", "--property", "RestartSec=2", "--property", "TimeoutStopSec=5",
         # rclpy's logging needs a home for its log directory (systemd-run gives the unit none).
         "--setenv", "HOME=/root",
         python, "/usr/local/lib/ccrp/ccrp-demo-node"],
        role="robot-sim",
    )
    if rc != 0:
        raise CcrpError(f"cannot start the demo node on simulated robot {robot}: {out.strip()[-200:]}")
    return c.id[:12]


def start_device(provider: DockerHost, robot: str, bundle: Sequence) -> str:
    """(Re)create the simulated robot's power device: a container of its own beside the robot (same
    image and network), sharing only the robot's power line (POWER_DIR), with the device bundle
    installed as on a real device. It reads the robot's state from the supply's file."""
    robot_c = provider.running_container(robot, role="robot-sim")
    stop_device(provider, robot)
    network = next(iter(robot_c.attrs["NetworkSettings"]["Networks"]))
    robot_state = f"CCRP_POWER_ROBOT_COMMAND=cat {POWER_DIR}/robot\n".encode()
    c = _create(provider, robot, "power-sim", robot_c.image.id, network, bundle,
                [("etc/ccrp/power.env", robot_state, 0o644)], hostname=f"{robot}-power",
                volumes=["/sys/fs/cgroup:/sys/fs/cgroup:ro"], volumes_from=[robot_c.id])
    return c.id[:12]


def stop_device(provider: DockerHost, robot: str) -> bool:
    c = provider.container(robot, role="power-sim")
    if c is None:
        return False
    c.remove(force=True, v=True)
    return True


def stop(provider: DockerHost, robot: str) -> bool:
    stop_device(provider, robot)  # first: it holds the robot's power line volume
    c = provider.container(robot, role="robot-sim")
    if c is None:
        return False
    # Shut down as a robot is switched off: its OpenVPN tells the clone it leaves (explicit-exit-
    # notify), so the session ends now instead of at the keepalive timeout, a minute or two later.
    c.stop(timeout=10)
    c.remove(force=True, v=True)
    return True


class RobotContainers(DockerHost):
    """A fleet's simulated robots and power devices on this host's engine (base.RobotHost)."""

    def running(self, robot: str) -> bool:
        c = self.container(robot, role="robot-sim")
        return c is not None and c.status == "running"

    def names(self, running: bool = False) -> list[str]:
        found = self.engine.containers.list(all=not running, ignore_removed=True, filters=self.filters("robot-sim"))
        return sorted(c.labels.get(LABEL_ROBOT, "") for c in found)

    def exec(self, robot: str, argv: list[str], timeout: float = 60, role: str = "robot-sim") -> tuple[int, str]:
        return super().exec(robot, argv, timeout=timeout, role=role)

    def push_files(self, robot: str, files: Sequence, restart: Sequence[str] = (), role: str = "robot-sim") -> None:
        super().push_files(robot, files, restart, role=role)

    def robot_image(self, distro: str, progress=lambda msg: None) -> str:
        return sim_image(self, distro, progress)

    def start(self, robot: str, image: str, bundle: Sequence, demo_node: str, attachment: RobotAttachment,
              python: str = "/usr/bin/python3") -> str:
        return start(self, robot, image, bundle, demo_node, attachment.network, python, attachment.attach)

    def stop(self, robot: str) -> bool:
        return stop(self, robot)

    def start_device(self, robot: str, bundle: Sequence) -> str:
        return start_device(self, robot, bundle)

    def close(self) -> None:
        self.engine.close()
