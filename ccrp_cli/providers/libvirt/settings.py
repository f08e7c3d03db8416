"""`provider:` of an inventory for the libvirt backend."""

from __future__ import annotations

import ipaddress
import re
from collections.abc import Mapping
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, model_validator

from ...models.strict import ProviderSettings, Strict
from ...errors import InputError, shown

# A libvirt connection URI as `virsh -c` takes it: driver[+transport]://[user@][host][:port]/path[?query],
# one token (no space, quote, shell character or percent-escape: a parameter is read as written):
# qemu:///system, qemu+ssh://ops@lab1/system...
_URI_RE = re.compile(r"(?P<scheme>[a-z][a-z0-9]*(\+[a-z0-9]+)?)://(?:(?P<user>[A-Za-z0-9_][A-Za-z0-9._-]*)@)?"
                     r"(?P<host>[A-Za-z0-9][A-Za-z0-9.-]*|\[[0-9A-Fa-f:.]+\])?(?::(?P<port>[0-9]{1,5}))?"
                     r"(?P<path>/[A-Za-z0-9._/-]*)(?:\?(?P<query>[A-Za-z0-9._=&/-]*))?", re.ASCII)
# The transports ccrp opens: this machine's libvirtd over its Unix socket (qemu:///system,
# qemu+unix:///system) or another host's over SSH or TLS, whose host key or certificate libvirt
# verifies. Not `ext` (it runs the URI's command= on this machine), nor `tcp` (no encryption and no
# check of the host: a man in the middle would feed the serial console that the clones' SSH host keys
# are pinned from, and then receive the keys ccrp pushes), nor libssh/libssh2 (known_hosts_verify=
# turns their check off, and the system's ssh client serves the same hosts).
URI_SCHEMES = ("qemu", "qemu+unix", "qemu+ssh", "qemu+tls")
URI_PATHS = ("/system", "/session")
# The URI parameters an inventory may give (libvirt's remote URI parameters, docs/libvirt.md): each
# chooses among what the operator's machine and the libvirt host already trust, and none runs a
# program or weakens a check. keyfile: which private key ssh offers the host (it proves who ccrp is;
# the host's own key is still checked against known_hosts). mode, proxy: which daemon on the host
# serves the connection, and which of libvirt's own helpers (virt-ssh-helper or nc) reaches it.
# libvirt reads parameter names in any case.
URI_PARAMS: dict[str, tuple[str, ...] | None] = {"keyfile": None, "mode": ("auto", "direct", "legacy"),
                                                 "proxy": ("auto", "native", "netcat")}
# Why the others are refused (issue 39); a name not listed here is refused too, as one ccrp does not know.
_REFUSED = {
    "command": "runs a program on this machine",
    "netcat": "names a program run on the libvirt host",
    "socket": "names another socket than libvirtd's (over ssh, in a command run on the host)",
    "no_verify": "turns off the check of the host's SSH key or TLS certificate",
    "no_tty": "changes how the ssh client runs (BatchMode belongs in ~/.ssh/config)",
    "known_hosts": "names the host keys trusted",
    "known_hosts_verify": "can turn off the check of the host's SSH key",
    "sshauth": "changes how libssh authenticates",
    "pkipath": "names the CA the host's certificate is checked against",
    "tls_priority": "can let TLS use weak versions and ciphers",
    "name": "names the URI the libvirt host opens, with parameters of its own",
}
# The operator's own parameters for every URI ccrp opens (a wrapper ssh command that pins the host's
# key, as tests/e2e/test_libvirt_remote.py gives): from the environment, never from an inventory,
# added to the query as given.
URI_PARAMS_ENV = "CCRP_LIBVIRT_URI_PARAMS"
# A storage pool's name and directory on the libvirt host: one token each.
_POOL_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", re.ASCII)
_DIR_RE = re.compile(r"/[A-Za-z0-9._/-]{1,200}", re.ASCII)
# The URIs of a libvirt host that is this machine (its bridges and firewall are ccrp's to touch).
LOCAL_URIS = frozenset({"qemu:///system", "qemu+unix:///system"})
_HINT = f"an inventory's URI takes {', '.join(URI_PARAMS)}; this machine's own go in {URI_PARAMS_ENV}"


def _uri(text: str) -> str:
    m = _URI_RE.fullmatch(text)
    if not m or len(text) > 255:
        raise ValueError(f"{shown(text)} is not a libvirt URI (qemu:///system, qemu+ssh://user@host/system)")
    scheme, host = m["scheme"], m["host"]
    if scheme not in URI_SCHEMES:
        raise ValueError(f"transport {scheme} is refused: ccrp opens {', '.join(URI_SCHEMES)} "
                         f"(ext runs a program here, tcp neither encrypts nor checks the host)")
    if scheme in ("qemu+ssh", "qemu+tls") and not host:
        raise ValueError(f"{shown(text)}: {scheme} needs a host ({scheme}://user@host/system)")
    if scheme == "qemu+unix" and (host or m["user"] or m["port"]):
        raise ValueError(f"{shown(text)}: qemu+unix is this machine's socket, with no host (qemu+unix:///system)")
    if m["path"] not in URI_PATHS:
        raise ValueError(f"{shown(text)}: path {m['path']} is not the QEMU driver's {' or '.join(URI_PATHS)}")
    for item in (m["query"] or "").split("&"):
        if not item:
            continue
        name, _, value = item.partition("=")
        key = name.lower()
        if key not in URI_PARAMS:
            why = f"it {_REFUSED[key]}" if key in _REFUSED else "ccrp does not know it"
            raise ValueError(f"parameter {name} is refused: {why} ({_HINT})")
        allowed = URI_PARAMS[key]
        if allowed is not None and value not in allowed:
            raise ValueError(f"parameter {name}={value}: give one of {', '.join(allowed)}")
        if not value:
            raise ValueError(f"parameter {name} has no value")
        if key == "keyfile" and not value.startswith("/"):  # a file of this machine, never read as an option
            raise ValueError(f"parameter keyfile={value}: give the key's absolute path")
    return text


def connect_uri(uri: str, environ: Mapping[str, str]) -> str:
    """The URI ccrp opens: the inventory's, with the operator's own parameters (URI_PARAMS_ENV) added."""
    extra = environ.get(URI_PARAMS_ENV, "").strip().strip("&")
    if not extra:
        return uri
    if any(c.isspace() or c == "#" for c in extra):
        raise InputError(f"{URI_PARAMS_ENV} {shown(extra)} is not a URI query (name=value&name=value, no spaces)")
    return f"{uri}{'&' if '?' in uri else '?'}{extra}"


def _pool(text: str) -> str:
    if not _POOL_RE.fullmatch(text):
        raise ValueError(f"{shown(text)} is not a storage pool name (letters, digits, . _ -)")
    return text


def _dir(text: str) -> str:
    if not _DIR_RE.fullmatch(text) or "/../" in f"{text}/" or "//" in text:
        raise ValueError(f"{shown(text)} is not an absolute directory path")
    return text


class VpnForward(Strict):
    """Robots outside the libvirt host dial `address` (one of the host's, on their LAN) at
    `base_port` plus their clone's offset in the addressing plan; the host forwards that port to
    the clone's VPN port and nothing else (forward.py)."""

    address: ipaddress.IPv4Address
    base_port: Annotated[int, Field(strict=True, ge=1024, le=65_000)] = 11940

    @model_validator(mode="after")
    def _an_address_robots_can_dial(self) -> "VpnForward":
        a = self.address
        if a.is_loopback or a.is_unspecified or a.is_multicast or a.is_link_local:
            raise ValueError(f"vpn_forward.address {a} is not an address robots can dial (give the host's LAN address)")
        return self


class LibvirtSettings(ProviderSettings):
    kind: Literal["libvirt"]
    uri: Annotated[str, AfterValidator(_uri)] = "qemu:///system"
    # kvm: hardware virtualisation; tcg: QEMU's emulation (slow, works anywhere); auto: kvm when a
    # probe VM really boots with it, tcg otherwise (a /dev/kvm that opens is not proof: docs/libvirt.md).
    accel: Literal["auto", "kvm", "tcg"] = "auto"
    memory_mb: Annotated[int, Field(strict=True, ge=512, le=262_144)] = 2048
    vcpus: Annotated[int, Field(strict=True, ge=1, le=64)] = 2
    # Quotas before growth (provider.quotas): the host's CPUs times this are the vCPUs its running
    # domains may have in all. 4.0 is OpenStack Nova's initial_cpu_allocation_ratio: vCPUs are
    # threads of QEMU that share cores (slower, not refused); 1.0 keeps one core per vCPU.
    vcpu_overcommit: Annotated[float, Field(strict=True, ge=1.0, le=64.0)] = 4.0
    # What one clone's qcow2 overlay is expected to take of the storage pool, held before a clone is
    # created (and, for a clone's overlay already there, what it has not taken yet). An overlay holds
    # only the clone's writes: 20-25 MB after its first boot here (docs/libvirt.md); the rest is room
    # for journald (by default up to 10% of the 8 GiB root file system: 819 MiB) and ROS logs. The
    # worst case is the golden volume's virtual size (8 GiB): an overlay can grow to it.
    overlay_mb: Annotated[int, Field(strict=True, ge=64, le=1_048_576)] = 1024
    # The fleet's NAT network (plays the clouds' public network): the host is its first address,
    # clones get theirs from its DHCP range.
    public_cidr: ipaddress.IPv4Network = ipaddress.IPv4Network("192.168.150.0/24")
    # Where SSH to the clones may come from (their firewall, templates/clone/firewall.rules.j2): by
    # default the libvirt host's own address on the NAT network, the one way in from outside it.
    operator_cidr: ipaddress.IPv4Network | None = None
    # The storage pool (a directory on the libvirt host) holding golden volumes, overlays, seeds
    # and consoles; created by `fleet up` when missing, shared by fleets, never removed by ccrp.
    pool: Annotated[str, AfterValidator(_pool)] = "ccrp"
    pool_dir: Annotated[str, AfterValidator(_dir)] = "/var/lib/libvirt/images/ccrp"
    # Robots outside the libvirt host reach their clones' VPN port through it (None: only robots on
    # the host itself, as `ccrp robot sim` makes them, reach the clones).
    vpn_forward: VpnForward | None = None

    def networks(self) -> dict[str, ipaddress.IPv4Network]:
        return {"provider.public_cidr": self.public_cidr}

    def operator_network(self) -> ipaddress.IPv4Network | None:
        return self.operator_cidr

    @model_validator(mode="after")
    def _operator_is_the_host(self) -> "LibvirtSettings":
        if self.operator_cidr is None:
            self.operator_cidr = ipaddress.IPv4Network(f"{next(self.public_cidr.hosts())}/32")
        fwd = self.vpn_forward
        if fwd is not None:
            if self.uri not in LOCAL_URIS:
                raise ValueError(f"vpn_forward is made by this machine's firewall, and provider.uri {self.uri} is another "
                                 f"machine's libvirt (forward the VPN ports there, or run ccrp on that host)")
            if fwd.address in self.public_cidr:
                raise ValueError(f"vpn_forward.address {fwd.address} is in provider.public_cidr {self.public_cidr}: "
                                 f"give the host's address on the robots' LAN")
            if fwd.base_port + self.public_cidr.num_addresses > 65_535:
                raise ValueError(f"vpn_forward.base_port {fwd.base_port} leaves no port for the last addresses of "
                                 f"{self.public_cidr}: at most {65_535 - self.public_cidr.num_addresses}")
        return self
