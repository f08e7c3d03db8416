"""ROS environment, /etc/hosts blocks, chrony and firewall: per vantage point."""

from __future__ import annotations

from ..models.addressing import gateway_ip
from ..templates import render
from .view import CloneView

HOSTS_BEGIN, HOSTS_END = "# BEGIN ccrp", "# END ccrp"
# Where a ROS 2 robot's edge bundle installs its Fast DDS profile (templates/edge/fastdds.xml.j2).
ROBOT_FASTDDS_PROFILE = "/etc/ccrp/fastdds.xml"


# ROS 2 domains (docs/ros2.md): 1..100, the range whose RTPS ports (7400 + 250 * domain + up to
# 249) stay below Linux's ephemeral ports (32768 and up) whatever the participant id.
DOMAIN_COUNT = 100
# RTPS's default port mapping: PB + DG * domain, each domain using DG ports.
RTPS_PB, RTPS_DG = 7400, 250


def ros_domain(index: int) -> int:
    """A robot's ROS_DOMAIN_ID, from its slot (addressing.allocate): slot k gets ((k - 1) % 100) + 1,
    so the first 100 robots each have their own domain, and a slot keeps its domain for life."""
    return (index - 1) % DOMAIN_COUNT + 1


def rtps_ports(index: int) -> tuple[int, int]:
    """The UDP port range the robot's domain uses (first, last)."""
    first = RTPS_PB + RTPS_DG * ros_domain(index)
    return first, first + RTPS_DG - 1


def ros_env(view: CloneView, side: str) -> str:
    """KEY=VALUE lines (systemd EnvironmentFile and POSIX shell). side: clone | robot."""
    a, ros = view.addr, view.inv.ros
    if ros.ros2:
        # No master: each side's only DDS peer is the other end of the tunnel, by unicast, and no
        # multicast anywhere (LOCALHOST). The same domain on both ends, its own per robot.
        peer = a.robot_vpn_ip if side == "clone" else a.clone_vpn_ip
        env = {
            "ROS_DISTRO": ros.distro,
            "ROS_DOMAIN_ID": str(ros_domain(a.index)),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "ROS_STATIC_PEERS": str(peer),
            "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
            "CCRP_FLEET": view.fleet,
            "CCRP_ROBOT": view.name,
        }
        if side == "robot":
            # The robot's participants announce its VPN address whenever they started, tunnel up or
            # not (fastdds.xml.j2). Fast DDS 2 (Jazzy) reads the first name, Fast DDS 3 (Kilted) the second.
            env["FASTRTPS_DEFAULT_PROFILES_FILE"] = env["FASTDDS_DEFAULT_PROFILES_FILE"] = ROBOT_FASTDDS_PROFILE
        return "".join(f"{k}={v}\n" for k, v in env.items())
    env = {
        "ROS_DISTRO": ros.distro,
        "ROS_MASTER_URI": f"http://{a.clone_host}:{ros.master_port}",
        "ROS_MASTER_PORT": str(ros.master_port),
        "ROS_HOSTNAME": a.clone_host if side == "clone" else view.name,
        "CCRP_FLEET": view.fleet,
        "CCRP_ROBOT": view.name,
    }
    return "".join(f"{k}={v}\n" for k, v in env.items())


def hosts_block(view: CloneView, side: str) -> str:
    """The clone resolves itself to loopback (so ROS starts whatever the VPN's state), its robot
    over the VPN, and the other clones on the common network. The robot resolves only itself
    and its own clone."""
    a = view.addr
    if side == "clone":
        rows = [("127.0.1.1", a.clone_host), (str(a.robot_vpn_ip), view.name)]
    else:
        rows = [(str(a.clone_vpn_ip), a.clone_host), (str(a.robot_vpn_ip), view.name)]
    body = "".join(f"{ip:<15} {host}\n" for ip, host in rows)
    if side == "clone":
        body += "".join(p.hosts_line for p in view.peers)
    return f"{HOSTS_BEGIN}\n{body}{HOSTS_END}\n"


def clone_hosts_file(view: CloneView) -> str:
    return (
        "127.0.0.1       localhost\n::1             localhost ip6-localhost ip6-loopback\n"
        + hosts_block(view, "clone")
    )


def chrony_conf(view: CloneView, side: str) -> str:
    a = view.addr
    if side == "clone":
        # Serve time to the robot even while the clone itself is not synchronised.
        return f"# ccrp: serve time to robot {view.name} over its VPN\nallow {a.vpn_subnet}\nlocal stratum 10\n"
    return f"# ccrp: take time from clone {a.clone_host} over the VPN\nserver {a.clone_vpn_ip} iburst prefer\n"


def firewall_rules(view: CloneView) -> tuple[str, str]:
    """(iptables-restore, ip6tables-restore) rules of the clone. Behind an entry gateway, ccrp's SSH
    comes from the gateway's common address (render/gateway.py)."""
    ports = rtps_ports(view.addr.index) if view.inv.ros.ros2 else None
    jump = gateway_ip(view.inv) if view.inv.provider.entry == "gateway" else None
    return (render("clone/firewall.rules.j2", **view.ctx(rtps_ports=ports, gateway_ip=jump)),
            render("clone/firewall6.rules.j2", **view.ctx(rtps_ports=ports)))
