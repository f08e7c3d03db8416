"""cloud-init user-data of a clone: a dict dumped with yaml.safe_dump. Never a private key."""

from __future__ import annotations

import ast
import functools
import re
import threading
from typing import TYPE_CHECKING, Any, Sequence

import yaml

from ..errors import CcrpError
from ..models.layout import (CCRP_ETC, ROS2_RMEM, ROS2_SYSCTL, CCRP_LIB, LOCALE, LOCALE_SETUP, LOGIN_USER, SECRETS_DIR,
                      VPN_DIR)
from ..models.inventory import Inventory
from ..providers.registry import info
from ..recipes import platform
from ..resources import agent_source
from ..templates import render, static
from . import network, openvpn
from .view import CloneView

if TYPE_CHECKING:
    from .boot import Boot

PRIVATE_KEY_MARKERS = ("PRIVATE KEY", "OpenVPN Static key")


def _file(path: str, content: str, mode: str = "0644") -> dict[str, Any]:
    if path.endswith(".py"):
        content = compact_python(content)
    return {"path": path, "content": content, "permissions": mode, "owner": "root:root"}


def _docstrings(tree) -> list:
    """The docstring statements of a module, its classes and functions."""
    return [node.body[0] for node in ast.walk(tree)
            if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body
            and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)
            and isinstance(node.body[0].value.value, str)]


def compact_shell(src: str) -> str:
    """A shell script (or a systemd unit) as user-data carries it: its comment lines gone, its first
    line (a shebang) kept, as agents' sources are compacted: AWS takes 16 KiB gzipped. Only for
    text with no here-document or multi-line string, where a line starting with # is always a comment."""
    return "".join(line for i, line in enumerate(src.splitlines(keepends=True))
                   if i == 0 or not line.lstrip().startswith("#"))


_COMPACTING = threading.Lock()


@functools.lru_cache(maxsize=32)
def compact_python(src: str) -> str:
    """Once per source and one at a time: `fleet up` renders clones in threads, and CPython 3.11's
    ast module is not thread-safe ("AST constructor recursion depth mismatch")."""
    with _COMPACTING:
        return _compact_python(src)


def _compact_python(src: str) -> str:
    """An agent's source as user-data carries it: without comments, blank lines and docstrings
    (each becomes `pass`), every other character as written. User-data has a hard limit (AWS:
    16 KiB gzipped) and a clone needs only the code; snapshots carry the source whole. Returns
    `src` itself unless the result parses to the same program."""
    import io
    import tokenize

    lines = src.splitlines(keepends=True)
    drop = set()
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        row = tok.start[0] - 1
        if tok.type == tokenize.NL and not tok.line.strip():  # a blank line, not one inside a string
            drop.add(row)
        elif tok.type == tokenize.COMMENT and not (row == 0 and tok.string.startswith("#!")):
            if lines[row][:tok.start[1]].strip():
                lines[row] = lines[row][:tok.start[1]].rstrip() + "\n"
            else:
                drop.add(row)
    stripped, module = set(), ast.parse(src)
    for doc in _docstrings(module):
        first, last = lines[doc.lineno - 1], lines[doc.end_lineno - 1]
        if first[:doc.col_offset].strip() or last[doc.end_col_offset:].strip():
            continue  # shares a line with other code: left as it is
        drop |= set(range(doc.lineno, doc.end_lineno))
        # A function's may be its whole body; the module's goes (`from __future__` must come first).
        lines[doc.lineno - 1] = first[:doc.col_offset] + "pass\n"
        if doc is module.body[0]:
            drop.add(doc.lineno - 1)
        stripped.add((doc.lineno, doc.col_offset))
    out = "".join(line for i, line in enumerate(lines) if i not in drop)
    want = module  # the program expected: docstrings as `pass`, the module's gone
    if want.body and (getattr(want.body[0], "lineno", 0), getattr(want.body[0], "col_offset", 0)) in stripped:
        want.body = want.body[1:]
    for node in ast.walk(want):
        for field in ("body", "orelse", "finalbody"):
            block = getattr(node, field, None)
            if isinstance(block, list):
                setattr(node, field, [ast.Pass() if isinstance(s, ast.Expr) and (s.lineno, s.col_offset) in stripped
                                      else s for s in block])
    try:
        compile(out, "<agent>", "exec", dont_inherit=True)
        return out if ast.dump(ast.parse(out)) == ast.dump(want) else src
    except SyntaxError:
        return src


def ros2_sysctl() -> str:
    return ("# ccrp: receive buffers for ROS 2's UDP (a 320x240 image is four 64 KB datagrams)\n"
            f"net.core.rmem_default = {ROS2_RMEM}\nnet.core.rmem_max = {ROS2_RMEM}\n")


# A ROS 2 clone's graph keeper (ccrp-graph.service: agent/ros2_graph.py serve) runs as a user of its own.
GRAPH_USER = "ccrp-graph"
# So does a ROS 1 clone's master (ccrp-rosmaster.service): not `ros`, whose nodes are the user's code
# and could otherwise write its home or signal and trace it.
MASTER_USER = "ccrp-rosmaster"


def base_units(inv: Inventory) -> list[str]:
    """The base's systemd units: the firewall, OpenVPN and a ROS 1 clone's master, or on a ROS 2 clone
    its graph keeper in its place. The services' units follow them (their Boot declarations)."""
    return ["ccrp-firewall.service", "ccrp-openvpn.service",
            "ccrp-graph.service" if inv.ros.ros2 else "ccrp-rosmaster.service"]


def _system_user(name: str, **home: Any) -> dict[str, Any]:
    return {"name": name, "system": True, "shell": "/usr/sbin/nologin", "lock_passwd": True, **(home or {"no_create_home": True})}


def _unit(name: str) -> dict[str, Any]:
    """A unit as user-data carries it: its comment lines gone, as a script's (they say why, in
    templates/systemd/; a bare ROS 2 clone's user-data had 265 bytes to spare under AWS's 16 KiB
    gzipped). Its first line is its [Unit] section."""
    return _file(f"/etc/systemd/system/{name}", compact_shell(static(f"systemd/{name}")))


def user_data_dict(
    view: CloneView,
    boots: Sequence[Boot],
    *,
    install_packages: bool = False,
    login_keys: list[str] | None = None,
) -> dict[str, Any]:
    """The base (OpenVPN, ROS, the firewall, the login user), then what each clone service declares
    for the user-data (`boots`: services/registry.py boots(), in the registry's order).

    A cloud clone gets `login_keys` (the fleet's operator key) for LOGIN_USER, the one login ccrp's
    SSH transport uses; without them (Docker) the clone has no login user at all."""
    a = view.addr
    ros2 = view.inv.ros.ros2
    fw4, fw6 = network.firewall_rules(view)
    units = base_units(view.inv)
    files = [
        _file("/etc/hosts", network.clone_hosts_file(view)),
        _file(f"{CCRP_ETC}/hosts", network.clone_hosts_file(view)),  # put back at every boot (bootcmd)
        _file(f"{CCRP_ETC}/ros.env", network.ros_env(view, "clone")),
        _file("/etc/profile.d/ccrp-ros.sh", static("edge/ccrp-ros.sh")),
        _file(f"{CCRP_ETC}/firewall.rules", fw4, "0600"),
        _file(f"{CCRP_ETC}/firewall6.rules", fw6, "0600"),
        _file("/etc/chrony/conf.d/ccrp.conf", network.chrony_conf(view, "clone")),
        _file(f"{VPN_DIR}/server.conf", openvpn.server_conf(view)),
        _file(f"{VPN_DIR}/ccd/{view.name}", openvpn.ccd_entry(view)),
        _file(f"{VPN_DIR}/ccrp-auth", compact_python(static("clone/ccrp-auth")), "0755"),  # a python script
        _file(f"{CCRP_LIB}/ros-run", compact_shell(static("clone/ros-run")), "0755"),
        *(_unit(u) for u in units),
    ]
    if ros2:
        # A ROS 2 clone's graph for health.py (ccrp-graph.service); the image holds only the wheels'
        # venv (providers/docker/images.py).
        files.append(_file(f"{CCRP_LIB}/ros2_graph.py", agent_source("ros2_graph"), "0644"))
    sockets: list[str] = []
    for boot in boots:
        agents = boot.agents + (boot.ros2_agents if ros2 else ())
        files += [_file(f"{CCRP_LIB}/{name}.py", agent_source(name), boot.agent_mode) for name in agents]
        files += [_file(f.dest, f.content, f"{f.mode:04o}") for f in boot.files(view)]
        files += [_unit(u) for u in boot.units]
        files += [_file(f"/etc/systemd/system/{s}", render(f"systemd/{s}.j2", **view.ctx())) for s in boot.sockets]
        units += boot.units
        sockets += boot.sockets

    # A clone with its own kernel takes ROS 2's receive buffers from here (a container cannot).
    sysctl = ros2 and info(view.inv.provider.kind).own_kernel
    if sysctl:
        files.append(_file(ROS2_SYSCTL, ros2_sysctl()))

    # No "default": the images' own login users differ per cloud, so ccrp defines its own and the
    # image's is not created (keys from the cloud's key pair then go to root, with logins refused).
    users: list[Any] = [login_user(login_keys)] if login_keys else []
    users += [_system_user("openvpn"), _system_user("ros", homedir="/var/lib/ros")]
    users += [_system_user(GRAPH_USER if ros2 else MASTER_USER)]
    users += [_system_user(u) for boot in boots for u in boot.users]
    data: dict[str, Any] = {
        "hostname": a.clone_host,
        "preserve_hostname": False,
        "manage_etc_hosts": False,
        "users": users,
        "write_files": files,
        "runcmd": [
            # systemd-sysctl applies it at every later boot; at the first, it ran before the file. A
            # "VM" that is a container (the fake clouds' servers) cannot: said on the console, not fatal.
            *([["sh", "-c", 'sysctl -q -p "$0" || echo "ccrp: $0 not applied (no kernel of its own?)"', ROS2_SYSCTL]]
              if sysctl else []),
            # 0751: the relay user may open relay.key by name; nobody else may list the secrets.
            ["install", "-d", "-m", "0751", "-o", "root", "-g", "openvpn", VPN_DIR],
            ["install", "-d", "-m", "0755", "-o", "ros", "-g", "ros", "/var/lib/ros"],
            # One reload for all: each costs seconds on an emulated VM (7-8 s under TCG, 3 per boot
            # before), and `enable` alone would reload again. The enable links are for later boots.
            ["systemctl", "daemon-reload"],
            ["systemctl", "enable", "--no-reload", *sockets, *units],
            # Alone and first: the ports are systemd's before any of ccrp's services (and their users)
            # run. From the next boot on, sockets.target orders them before them.
            *([["systemctl", "start", *sockets]] if sockets else []),
            ["systemctl", "start", *units],
            ["systemctl", "try-restart", "chrony.service"],
        ],
        "final_message": f"ccrp clone {a.clone_host} of fleet {view.fleet} configured after $UPTIME s",
    }
    if info(view.inv.provider.kind).secrets == "memory":
        # bootcmd runs at every boot, before sshd: ccrp can only push into memory. After a
        # reboot the keys are gone and `ccrp fleet up` pushes them again.
        data["bootcmd"] = every_boot_bootcmd()
    if install_packages:
        # A bare base image: install at boot what a snapshot would already contain, but of its
        # agents only the services' bare_agents (the API manager's comes with `fleet up`).
        image = image_config(view.inv, [a for boot in boots for a in boot.bare_agents])
        files += image.pop("write_files")
        data["runcmd"][:0] = image.pop("runcmd")
        data.update(image)
    return data


def login_user(keys: list[str]) -> dict[str, Any]:
    return {"name": LOGIN_USER, "shell": "/bin/bash", "sudo": "ALL=(ALL) NOPASSWD:ALL", "lock_passwd": True,
            "ssh_authorized_keys": list(keys)}


def every_boot_bootcmd() -> list[list[str]]:
    """What a cloud clone does at every boot: put ccrp's /etc/hosts back, and mount a small tmpfs on
    SECRETS_DIR unless something (a volume) is mounted there already, root-only until ccrp hands it
    to the openvpn group just before pushing."""
    return [
        # The clone resolves itself through /etc/hosts (ROS_HOSTNAME), which some images' agents
        # rewrite at boot (GCE's guest agent manages it): from the second boot on, ccrp's is put back.
        ["sh", "-c", 'if [ -f "$0" ]; then cp "$0" /etc/hosts; fi', f"{CCRP_ETC}/hosts"],
        ["mkdir", "-p", SECRETS_DIR],
        ["sh", "-c", 'mountpoint -q "$0" || mount -t tmpfs -o mode=0700,size=4m,nosuid,nodev,noexec ccrp-keys "$0"',
         SECRETS_DIR],
    ]


def image_config(inv: Inventory, agents: Sequence[str]) -> dict[str, Any]:
    """What a snapshot holds beyond its base image, as cloud-config: what the Docker snapshot holds
    (templates/docker/Dockerfile.j2), installed on a stock Debian 12 cloud image. That is the
    recipe's packages from Debian's archive, `agents` (agent/<name>.py: the services' image_agents,
    a bare clone's bare_agents) with their pinned packages from pip on a ROS 1 image, and the locale.
    A clone of a bare image runs it at first boot; `snapshot bake` runs it once on a builder
    instance."""
    plat = platform(inv.ros.distro, inv.clone_platform)
    # cloud-init's locale module is off here: it runs (config stage) before the packages are
    # installed (final stage) and fails where the image has not generated the locale yet. runcmd
    # sets it after the packages, when locale-gen and pip3 exist.
    data: dict[str, Any] = {"locale": "false", "package_update": True, "packages": list(plat.packages)}
    data["write_files"], data["runcmd"] = [], [["sh", "-c", LOCALE_SETUP]]
    if plat.ros_installed:
        # The image's own ROS 2 under /opt/ros/<distro> (an apt install, its setup.sh), used as it is:
        # the agents' packages go to the system python, and /opt/ros/<distro>/bin/python (what ccrp's
        # agents start) is a launcher that sources the distro's setup.sh, made only where none is.
        prefix = ros2_prefix(inv.ros.distro)
        data["write_files"].append(_file(f"{CCRP_LIB}/ros-python", static("image/ros-python"), "0755"))
        data["runcmd"] += [["env", "PIP_BREAK_SYSTEM_PACKAGES=1", "pip3", "install", "--no-cache-dir", *plat.pip],
                           ["sh", "-c", '[ -e "$0/bin/python" ] || ln -s "$1" "$0/bin/python"', prefix, f"{CCRP_LIB}/ros-python"]]
    elif plat.pip and inv.ros.ros2:
        # The ros-<distro>-* wheels in a venv at the distro's prefix, as the Docker image has them
        # (templates/docker/ros2-venv.j2), from the index here; the agents come with the clone's user-data.
        prefix = ros2_prefix(inv.ros.distro)
        data["write_files"].append(_file(f"{CCRP_LIB}/ros2-setup", static("image/ros2-setup"), "0755"))
        data["runcmd"] += [["python3", "-m", "venv", prefix],
                           [f"{prefix}/bin/pip", "install", "--no-cache-dir", *plat.pip, *plat.pip_source],
                           ["sh", f"{CCRP_LIB}/ros2-setup", prefix, inv.ros.distro]]
    elif plat.pip:
        data["write_files"] += [_file(f"{CCRP_LIB}/{name}.py", agent_source(name), "0755") for name in agents]
        # Debian's python is externally managed (PEP 668): pip installs next to it only when told to.
        data["runcmd"].append(["env", "PIP_BREAK_SYSTEM_PACKAGES=1", "pip3", "install", "--no-cache-dir", *plat.pip])
    return data


def ros2_prefix(distro: str) -> str:
    return f"/opt/ros/{distro}"


def _proof(token: str, what: str, argv: list[str]) -> list[str]:
    """A runcmd entry that prints "ccrp-bake <token> <what>-ok" on the console only if argv
    succeeds. The token is an argument ($0), so that line never appears in the user-data itself."""
    # tee: cloud-final's stdout reaches the console on cloud images; /dev/console makes sure.
    script = f'"$@" >/dev/null 2>&1 && echo "ccrp-bake $0 {what}-ok" | tee /dev/console'
    return ["sh", "-c", script, token, *argv]


# Each recipe package installed (dpkg's "install ok installed", as the Dockerfile checks), not merely known.
INSTALLED_SH = 'for p; do dpkg-query -W -f="\\${Status}" "$p" | grep -q "install ok installed" || exit 1; done'
# The locale generated and recorded (LOCALE_SETUP), so clones do not generate it at boot.
LOCALE_SH = f'grep -qx "LANG={LOCALE}" /etc/default/locale && locale -a | grep -qix "{LOCALE.replace("-", "")}"'


def bake_proofs(inv: Inventory) -> list[str]:
    """What a builder's console must show (as "ccrp-bake <token> <what>-ok") before it is captured."""
    plat = platform(inv.ros.distro, inv.clone_platform)
    return ["apt", "locale"] + (["pip"] if plat.pip else []) + (["ros"] if plat.ros_installed else [])


def builder_user_data(inv: Inventory, token: str, agents: Sequence[str], login_keys: list[str] | None = None) -> str:
    """User-data of the instance `snapshot bake` captures: the image config with `agents` (the
    services' image_agents, services/registry.py), a proof on the console per install step, and a
    final message carrying the token. No fleet, robot or private key in it.
    `login_keys`: a bake with software: (the fleet's packages and workspace) logs in over SSH after
    cloud-init to build it; the login gets the operator key and sudo, which the build's last step
    takes away before the capture (templates/image/software-bake.sh)."""
    plat = platform(inv.ros.distro, inv.clone_platform)
    data = image_config(inv, agents)
    # ccrp-topic, as in every Docker image; in snapshots only (a bare clone's user-data has no room
    # left for it: EC2 takes 16 KiB).
    data["write_files"].append(_file("/usr/local/bin/ccrp-topic", static("image/ccrp-topic"), "0755"))
    pip_names = [re.split(r"[=<>!~;\[ ]", p, maxsplit=1)[0] for p in plat.pip]
    data["runcmd"] += [_proof(token, "apt", ["sh", "-c", INSTALLED_SH, "installed", *data["packages"]]),
                       _proof(token, "locale", ["sh", "-c", LOCALE_SH])]
    if "pip" in bake_proofs(inv):
        python = f"{ros2_prefix(inv.ros.distro)}/bin/python" if inv.ros.ros2 and not plat.ros_installed else "python3"
        data["runcmd"] += [_proof(token, "pip", [python, "-m", "pip", "show", *pip_names])]
    if "ros" in bake_proofs(inv):
        # The image's ROS as ccrp's agents start it: rclpy, the RMW ros.env names, and Zenoh import.
        data["runcmd"] += [_proof(token, "ros", [f"{ros2_prefix(inv.ros.distro)}/bin/python", "-c",
                                                 "import rclpy, zenoh, cv2; from rclpy.impl.implementation_singleton "
                                                 "import rclpy_implementation"])]
    data["runcmd"] += [
        ["apt-get", "clean"],
        # Every clone must get its own machine-id on first boot (DHCP client ids derive from it).
        ["truncate", "-s", "0", "/etc/machine-id"],
        # A cloud may capture the builder running (OpenStack's libvirt driver does, without asking
        # the guest): what is still in its page cache would not be in the snapshot.
        ["sync"],
    ]
    # Without a `users` entry cloud-init would create the image's default user (admin, debian...)
    # with the cloud's key pair and sudo, and the snapshot would carry that login into every clone.
    # The builder creates ccrp's login user instead, with no key and no sudo: a clone's user-data
    # gives it both (cloud-init applies them to a user that exists).
    data["users"] = [login_user(login_keys) if login_keys else {"name": LOGIN_USER, "shell": "/bin/bash", "lock_passwd": True}]
    data["final_message"] = f"ccrp-bake {token} finished after $UPTIME s"
    return dump(data)


class _Dumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):  # libyaml when available: ~10x faster
    """Multi-line strings as literal blocks, so the user-data stays readable in a console."""


_Dumper.add_representer(
    str,
    lambda d, s: d.represent_scalar("tag:yaml.org,2002:str", s, style="|" if "\n" in s else None),
)


def dump(data: dict[str, Any]) -> str:
    text = "#cloud-config\n" + yaml.dump(data, Dumper=_Dumper, sort_keys=False, width=1000)
    # Secrets only ever travel through the transport after boot (docs/security.md).
    for marker in PRIVATE_KEY_MARKERS:
        if marker in text:
            raise CcrpError("refusing to render user-data that contains key material")
    return text


def user_data(view: CloneView, boots: Sequence[Boot], **kwargs: Any) -> str:
    return dump(user_data_dict(view, boots, **kwargs))
