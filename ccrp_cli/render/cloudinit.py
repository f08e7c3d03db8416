"""cloud-init user-data of a clone: a dict dumped with yaml.safe_dump. Never a private key."""

from __future__ import annotations

import re
from typing import Any

import yaml

from ..errors import CcrpError
from ..models.inventory import Inventory
from ..recipes import platform
from . import network, openvpn
from .templates import static
from .view import CCRP_ETC, CCRP_LIB, LOGIN_USER, RELAY_USER, SECRETS_DIR, VPN_DIR, CloneView


def agent_source(name: str) -> str:
    """Code that runs on a clone (ccrp_cli/agent/<name>.py), shipped as a file."""
    from pathlib import Path

    return (Path(__file__).resolve().parent.parent / "agent" / f"{name}.py").read_text()

PRIVATE_KEY_MARKERS = ("PRIVATE KEY", "OpenVPN Static key")


def _file(path: str, content: str, mode: str = "0644") -> dict[str, Any]:
    return {"path": path, "content": content, "permissions": mode, "owner": "root:root"}


def user_data_dict(
    view: CloneView,
    *,
    install_packages: bool = False,
    login_keys: list[str] | None = None,
) -> dict[str, Any]:
    """A cloud clone gets `login_keys` (the fleet's operator key) for LOGIN_USER, the one login ccrp's
    SSH transport uses; without them (Docker) the clone has no login user at all."""
    a = view.addr
    fw4, fw6 = network.firewall_rules(view)
    units = ["ccrp-firewall.service", "ccrp-openvpn.service", "ccrp-rosmaster.service", "ccrp-relay.service"]
    files = [
        _file("/etc/hosts", network.clone_hosts_file(view)),
        _file(f"{CCRP_ETC}/ros.env", network.ros_env(view, "clone")),
        _file("/etc/profile.d/ccrp-ros.sh", static("edge/ccrp-ros.sh")),
        _file(f"{CCRP_ETC}/firewall.rules", fw4, "0600"),
        _file(f"{CCRP_ETC}/firewall6.rules", fw6, "0600"),
        _file("/etc/chrony/conf.d/ccrp.conf", network.chrony_conf(view, "clone")),
        _file(f"{VPN_DIR}/server.conf", openvpn.server_conf(view)),
        _file(f"{VPN_DIR}/ccd/{view.name}", openvpn.ccd_entry(view)),
        _file(f"{VPN_DIR}/ccrp-auth", static("clone/ccrp-auth"), "0755"),
        _file(f"{CCRP_LIB}/ros-run", static("clone/ros-run"), "0755"),
    ] + [_file(f"/etc/systemd/system/{u}", static(f"systemd/{u}")) for u in units]

    # No "default": the images' own login users differ per cloud, so ccrp defines its own and the
    # image's is not created (keys from the cloud's key pair then go to root, with logins refused).
    users: list[Any] = [login_user(login_keys)] if login_keys else []
    users += [
        {"name": "openvpn", "system": True, "shell": "/usr/sbin/nologin", "lock_passwd": True, "no_create_home": True},
        {"name": "ros", "system": True, "shell": "/usr/sbin/nologin", "lock_passwd": True, "homedir": "/var/lib/ros"},
        {"name": RELAY_USER, "system": True, "shell": "/usr/sbin/nologin", "lock_passwd": True, "no_create_home": True},
    ]
    data: dict[str, Any] = {
        "hostname": a.clone_host,
        "preserve_hostname": False,
        "manage_etc_hosts": False,
        "users": users,
        "write_files": files,
        "runcmd": [
            # 0751: the relay user may open relay.key by name; nobody else may list the secrets.
            ["install", "-d", "-m", "0751", "-o", "root", "-g", "openvpn", VPN_DIR],
            ["install", "-d", "-m", "0755", "-o", "ros", "-g", "ros", "/var/lib/ros"],
            ["systemctl", "daemon-reload"],
            ["systemctl", "enable", "--now", *units],
            ["systemctl", "try-restart", "chrony.service"],
        ],
        "final_message": f"ccrp clone {a.clone_host} of fleet {view.fleet} configured after $UPTIME s",
    }
    if view.inv.provider.kind != "docker":
        # bootcmd runs at every boot, before sshd: ccrp can only push into memory. After a
        # reboot the keys are gone and `ccrp fleet up` pushes them again.
        data["bootcmd"] = secrets_tmpfs_bootcmd()
    if install_packages:
        # A bare base image: install at boot what a snapshot would already contain.
        image = image_config(view.inv)
        files += image.pop("write_files")
        data["runcmd"][:0] = image.pop("runcmd")
        data.update(image)
    return data


def login_user(keys: list[str]) -> dict[str, Any]:
    return {"name": LOGIN_USER, "shell": "/bin/bash", "sudo": "ALL=(ALL) NOPASSWD:ALL", "lock_passwd": True,
            "ssh_authorized_keys": list(keys)}


def secrets_tmpfs_bootcmd() -> list[list[str]]:
    """Mount a small tmpfs on SECRETS_DIR unless something (a volume) is mounted there already.
    Root-only until ccrp hands it to the openvpn group just before pushing."""
    return [
        ["mkdir", "-p", SECRETS_DIR],
        ["sh", "-c", 'mountpoint -q "$0" || mount -t tmpfs -o mode=0700,size=4m,nosuid,nodev,noexec ccrp-keys "$0"',
         SECRETS_DIR],
    ]


# The locale of every clone image, set as templates/docker/Dockerfile.j2 sets it (it renders this
# same command): generated once in the image and recorded in /etc/default/locale, so cloud-init's
# locale module finds it set and no clone runs locale-gen at boot (seconds of CPU each).
LOCALE = "en_US.UTF-8"
LOCALE_SETUP = (f"sed -i 's/^# *\\({LOCALE} UTF-8\\)/\\1/' /etc/locale.gen && locale-gen >/dev/null "
                f"&& update-locale LANG={LOCALE}")


def image_config(inv: Inventory) -> dict[str, Any]:
    """What a snapshot holds beyond its base image, as cloud-config: what the Docker snapshot holds
    (templates/docker/Dockerfile.j2), installed on a stock Debian 12 cloud image. That is the
    recipe's packages from Debian's archive, the relay agent and its pinned Zenoh from pip, and the
    locale. A clone of a bare image runs it at first boot; `snapshot bake` runs it once on a builder
    instance."""
    plat = platform(inv.ros.distro, inv.provider.kind)
    # cloud-init's locale module is off here: it runs (config stage) before the packages are
    # installed (final stage) and fails where the image has not generated the locale yet. runcmd
    # sets it after the packages, when locale-gen and pip3 exist.
    data: dict[str, Any] = {"locale": "false", "package_update": True, "packages": list(plat.packages)}
    data["write_files"], data["runcmd"] = [], [["sh", "-c", LOCALE_SETUP]]
    if plat.pip:
        data["write_files"].append(_file(f"{CCRP_LIB}/relay.py", agent_source("relay"), "0755"))
        # Debian's python is externally managed (PEP 668): pip installs next to it only when told to.
        data["runcmd"].append(["env", "PIP_BREAK_SYSTEM_PACKAGES=1", "pip3", "install", "--no-cache-dir", *plat.pip])
    return data


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
    return ["apt", "locale"] + (["pip"] if platform(inv.ros.distro, inv.provider.kind).pip else [])


def builder_user_data(inv: Inventory, token: str) -> str:
    """User-data of the instance `snapshot bake` captures: the image config, a proof on the console
    per install step, and a final message carrying the token. No fleet, robot or key in it."""
    plat = platform(inv.ros.distro, inv.provider.kind)
    data = image_config(inv)
    pip_names = [re.split(r"[=<>!~;\[ ]", p, maxsplit=1)[0] for p in plat.pip]
    data["runcmd"] += [_proof(token, "apt", ["sh", "-c", INSTALLED_SH, "installed", *data["packages"]]),
                       _proof(token, "locale", ["sh", "-c", LOCALE_SH])]
    if "pip" in bake_proofs(inv):
        data["runcmd"] += [_proof(token, "pip", ["python3", "-m", "pip", "show", *pip_names])]
    data["runcmd"] += [
        ["apt-get", "clean"],
        # Every clone must get its own machine-id on first boot (DHCP client ids derive from it).
        ["truncate", "-s", "0", "/etc/machine-id"],
    ]
    if not data["write_files"]:
        del data["write_files"]
    # Without a `users` entry cloud-init would create the image's default user (admin, debian...)
    # with the cloud's key pair and sudo, and the snapshot would carry that login into every clone.
    # The builder creates ccrp's login user instead, with no key and no sudo: a clone's user-data
    # gives it both (cloud-init applies them to a user that exists).
    data["users"] = [{"name": LOGIN_USER, "shell": "/bin/bash", "lock_passwd": True}]
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


def user_data(view: CloneView, **kwargs: Any) -> str:
    return dump(user_data_dict(view, **kwargs))
