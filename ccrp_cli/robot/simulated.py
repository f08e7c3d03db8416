"""Simulated robots of a fleet (`ccrp robot sim`): start, stop, and the emulated link to the clone.

A simulated robot is a container on this host (providers.robot_host) that installed exactly its
edge bundle. A backend whose fleet has a network of this host says where its robots sit on it
(Ability.ROBOT_ATTACH: Docker's public network, a port of libvirt's NAT bridge); for a cloud fleet
it dials its clone's public IP from a Docker network of this host.
"""

from __future__ import annotations

import re
import socket
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from ..errors import CcrpError, InputError, shown
from ..fleet import Fleet

if TYPE_CHECKING:
    from ..providers.base import Provider

Progress = Callable[[str], None]
LINK_UNIT = "ccrp-link"
LINK_PATH = "/usr/local/lib/ccrp/ccrp-link"


def stop_unit(execute: Callable[[list[str]], tuple[int, str]], unit: str) -> None:
    """Stop a transient systemd unit through `execute` (a clone's or a robot's exec), if it runs."""
    execute(["systemctl", "stop", unit])
    execute(["systemctl", "reset-failed", unit])


def run_unit(execute: Callable[[list[str]], tuple[int, str]], unit: str, argv: list[str], where: str,
             options: list[str] = ()) -> None:
    """(Re)start `argv` as the transient systemd unit `unit` through `execute`."""
    stop_unit(execute, unit)
    rc, out = execute(["systemd-run", "--unit", unit, *options, *argv])
    if rc != 0:
        raise CcrpError(f"cannot start {unit} on {where}: {out.strip()[-200:]}")


@dataclass(frozen=True)
class Link:
    """An emulated path between a simulated robot and its clone: round-trip delay, its jitter,
    and the packet loss of each direction."""

    rtt_ms: float
    jitter_ms: float = 0.0
    loss_pct: float = 0.0
    name: str = ""

    @property
    def spec(self) -> str:
        """As typed after --link (parse_link(spec) gives it back)."""
        return self.name or f"{self.rtt_ms:g}/{self.jitter_ms:g}/{self.loss_pct:g}"

    def __str__(self) -> str:
        return f"{self.spec} (rtt {self.rtt_ms:g} ms, jitter {self.jitter_ms:g} ms, loss {self.loss_pct:g} %)"


# Round trips from the UK measured in the thesis (Fig 7.1): about 50 ms to a GCP EU region and
# about 180 ms to a US region.
PRESETS = {"eu": Link(50, name="eu"), "us": Link(180, name="us")}
NO_LINK = ("none", "off")
_LINK_RE = re.compile(r"([0-9]+(?:\.[0-9]+)?)(?:/([0-9]+(?:\.[0-9]+)?))?(?:/([0-9]+(?:\.[0-9]+)?))?", re.ASCII)


def parse_link(text: str) -> Link | None:
    """eu | us | none | DELAY_MS[/JITTER_MS[/LOSS_PCT]]; None means: no emulated link."""
    if text in NO_LINK:
        return None
    if text in PRESETS:
        return PRESETS[text]
    m = _LINK_RE.fullmatch(text)
    if not m:
        raise InputError(f"--link {shown(text)} is not eu, us, none or DELAY_MS[/JITTER_MS[/LOSS_PCT]]",
                         hint="e.g. --link 80/5/0.5: 80 ms round trip, 5 ms jitter, 0.5 % loss each way")
    rtt, jitter, loss = (float(g) if g else 0.0 for g in m.groups())
    if rtt > 10_000 or jitter > rtt or loss >= 100:
        raise InputError(f"--link {shown(text)}: delay at most 10000 ms, jitter at most the delay, loss under 100 %")
    return Link(rtt, jitter, loss)


class Sims:
    """The simulated robots of one fleet and the clones they dial."""

    def __init__(self, fleet: Fleet, provider: Provider | None = None) -> None:
        from ..providers import Ability, get_provider, info, robot_host

        self.fleet = fleet
        self.kind = fleet.inventory.provider.kind
        self.attaches = Ability.ROBOT_ATTACH in info(self.kind).abilities
        self.clones = provider or get_provider(fleet.inventory)
        self.host = robot_host(fleet.name)

    def running(self, robot: str) -> bool:
        return self.host.running(robot)

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        return self.host.exec(robot, argv, timeout=timeout)

    def push(self, robot: str, files: list) -> None:
        self.host.push_files(robot, files)

    def start(self, robot: str, network: str | None = None, wait: float = 0, progress: Progress = lambda m: None) -> dict:
        """(Re)create the robot's simulated robot; with `wait`, until its node is on its clone."""
        from ..fleet import snapshot_image
        from ..providers.base import RobotAttachment
        from ..templates import static
        from .robots import edge_files

        state = self.fleet.store.load_state()
        self.fleet.robot(state, robot)
        # On the fleet's own network (ROBOT_ATTACH) the robot dials its clone's address there; with
        # --network it is outside, as a robot on the internet or a LAN, and dials the public endpoint,
        # which on such a fleet is a forward of the host (libvirt's provider.vpn_forward) or nothing.
        inside = self.attaches and not network
        # refuses a robot with no clone yet
        files, endpoint = edge_files(self.fleet, robot, self._inside(state, robot) if inside else None)
        if self.attaches and network and not self._forwarded(state, robot):
            raise InputError(f"--network puts the robot outside the {self.kind} fleet's own network, where its clone "
                             "has no way in", hint="leave --network out, or (libvirt) forward the VPN ports: "
                             "provider.vpn_forward (docs/libvirt.md)")
        if inside:
            seat = self.clones.attach_robot(robot, state.robots[robot].index)
        else:  # a cloud fleet's, or one outside: NATed by this host, as a robot on the internet
            seat = RobotAttachment(network=network or "bridge")
        if seat.clone_image:
            image = snapshot_image(state)
        else:
            image = self.host.robot_image(self.fleet.inventory.ros.distro, progress)
        t0 = time.monotonic()
        ros = self.fleet.inventory.ros
        if ros.ros2:  # the rclpy demo node, with the distro's python (docs/ros2.md)
            demo, python = static("edge/ccrp-demo-node2"), f"/opt/ros/{ros.distro}/bin/python"
        else:
            demo, python = static("edge/ccrp-demo-node"), "/usr/bin/python3"
        cid = self.host.start(robot, image, files, demo, seat, python)
        progress(f"simulated robot {robot!r} ({cid}) installed its bundle and dials {endpoint}"
                 + (f" from {seat.address} on {seat.name or seat.network}" if seat.address else ""))
        result = {"robot": robot, "container": cid, "endpoint": endpoint, "network": str(seat)}
        if wait > 0:
            from ..probe import wait_connected

            result |= wait_connected(self.clones, robot, wait)
            result["seconds"] = round(time.monotonic() - t0, 2)  # from container start to node registered
            progress(f"robot {robot!r} connected in {result['seconds']:.1f} s; nodes on its clone: {', '.join(result['nodes'])}")
        return result

    def stop(self, robot: str) -> bool:
        """Remove the simulated robot (and its power device, if it has one)."""
        stopped = self.host.stop(robot)
        if self.attaches:
            self.clones.detach_robot(robot)
        return stopped

    # -- its simulated power device (power.py) ---------------------------------------------------
    def start_device(self, robot: str, files: list) -> str:
        """(Re)create the robot's power device beside it, with the device bundle `files`."""
        return self.host.start_device(robot, files)

    def device_log(self, robot: str) -> str:
        try:
            _, out = self.host.exec(robot, ["journalctl", "-u", "ccrp-power-vpn", "-u", "ccrp-power-device", "-n", "8",
                                            "--no-pager"], timeout=10, role="power-sim")
        except CcrpError as exc:
            return exc.message
        return out.strip()

    def names(self, running: bool = False) -> list[str]:
        """The fleet's simulated robots on this host, running or not (with `running`: those that run)."""
        return self.host.names(running)

    def _inside(self, state, robot: str) -> str | None:
        """The clone's public address when the simulated robot sits on its network (ROBOT_ATTACH)."""
        rec = state.robots.get(robot)
        return (rec.addresses.get("public") or None) if self.attaches and rec is not None else None

    def _forwarded(self, state, robot: str) -> bool:
        """Whether robots outside the fleet's network dial the clone elsewhere than its address on it."""
        from ..models.values import parse_endpoint

        rec = state.robots.get(robot)
        if rec is None or not rec.public_endpoint or not rec.addresses.get("public"):
            return False
        return parse_endpoint(rec.public_endpoint, self.fleet.inventory.vpn.port).host != rec.addresses["public"]

    def clone_address(self, robot: str) -> str:
        """The IPv4 address the robot dials (its clone's public endpoint, resolved here)."""
        from ..models.values import parse_endpoint

        state = self.fleet.store.load_state()
        rec = state.robots.get(robot)
        if rec is None or not rec.public_endpoint:
            raise InputError(f"the clone of robot {robot!r} has no public endpoint yet", hint=f"ccrp clone create --robot {robot}")
        host = parse_endpoint(self._inside(state, robot) or rec.public_endpoint, self.fleet.inventory.vpn.port).host
        try:
            return socket.gethostbyname(host)
        except OSError as exc:
            raise CcrpError(f"cannot resolve {host}: {exc}") from None

    def set_link(self, robot: str, link: Link | None) -> None:
        """Shape (or, with None, stop shaping) the running robot's path to its clone, in place."""
        from ..render.files import BundleFile
        from ..templates import static

        execute = lambda argv: self.exec(robot, argv)  # noqa: E731
        if link is None:
            stop_unit(execute, LINK_UNIT)  # its rules go with it
            return
        self.push(robot, [BundleFile("ccrp-link", static("sim/ccrp-link"), 0o755, LINK_PATH)])
        run_unit(execute, LINK_UNIT, [
            "/usr/bin/python3", LINK_PATH, "--peer", self.clone_address(robot), "--rtt-ms", f"{link.rtt_ms:g}",
            "--jitter-ms", f"{link.jitter_ms:g}", "--loss-pct", f"{link.loss_pct:g}"],
            f"simulated robot {robot!r}", ["--description", str(link), "--property", "Restart=on-failure"])
        self._wait_link(robot)

    def _wait_link(self, robot: str) -> None:
        from ..retry import PollTimeout, poll

        def shaping() -> tuple[bool, str]:
            _, rules = self.exec(robot, ["iptables", "-w", "-t", "mangle", "-S", "OUTPUT"])
            return "NFQUEUE" in rules, rules

        try:
            poll(shaping, timeout=15, interval=0.1)
        except PollTimeout:
            _, log = self.exec(robot, ["journalctl", "-u", LINK_UNIT, "-n", "5", "--no-pager"])
            raise CcrpError(f"the link emulation of simulated robot {robot!r} did not start: {log.strip()[-300:]}") from None

    def link(self, robot: str) -> Link | None:
        """The link in effect on the running robot (None: the host's own network). Its unit's
        description starts with the link's spec."""
        rc, out = self.exec(robot, ["systemctl", "show", LINK_UNIT, "--property", "ActiveState,Description"])
        fields = dict(line.split("=", 1) for line in out.splitlines() if "=" in line)
        if fields.get("ActiveState") != "active":
            return None
        try:
            return parse_link(fields.get("Description", "").split(" ", 1)[0])
        except InputError:
            return None
