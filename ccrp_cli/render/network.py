"""ROS environment, /etc/hosts blocks, chrony and firewall: per vantage point."""

from __future__ import annotations

from .templates import render
from .view import CloneView

HOSTS_BEGIN, HOSTS_END = "# BEGIN ccrp", "# END ccrp"


def ros_env(view: CloneView, side: str) -> str:
    """KEY=VALUE lines (systemd EnvironmentFile and POSIX shell). side: clone | robot."""
    a, ros = view.addr, view.inv.ros
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
        rows += [(str(p.common_ip), p.clone_host) for p in view.peers]
    else:
        rows = [(str(a.clone_vpn_ip), a.clone_host), (str(a.robot_vpn_ip), view.name)]
    body = "".join(f"{ip:<15} {host}\n" for ip, host in rows)
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
    """(iptables-restore, ip6tables-restore) rules of the clone."""
    return render("clone/firewall.rules.j2", **view.ctx()), render("clone/firewall6.rules.j2", **view.ctx())
