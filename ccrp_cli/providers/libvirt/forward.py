"""Robots outside the libvirt host reach their clones through it (provider.vpn_forward): each
clone's VPN port is forwarded from a port of one of the host's addresses, and nothing else of it.

A clone's public address is on the fleet's NAT network, which only the host reaches: libvirt NATs
the clones' connections out and rejects new ones in (its LIBVIRT_FWI chain). So for each clone two
netfilter rules, made with the clone and removed with it:

- nat PREROUTING: `-d <address> -p <proto> --dport <port>` DNAT to `<clone public IP>:<vpn port>`;
- filter FORWARD, first: accept what that DNAT sent to the clone's VPN port (`--ctstate DNAT`),
  ahead of libvirt's reject and of Docker's DROP policy when a Docker engine runs here.

The clone's port on the host is `base_port` plus its offset in the addressing plan (its common
address's, as its public address is made), so it never changes for a robot. Replies are the
connection's own (conntrack) and leave as libvirt's rules already allow. Each rule carries the
comment `ccrp:<fleet>:<robot>`, which is how `fleet down`, `clone delete` and `gc` find them.

The rules are this machine's (iptables, the front end libvirt and Docker use here): only for a
libvirt host that is this machine (settings.py refuses vpn_forward with another URI). Commands are
argument lists; every token is an address, a number or a name checked by the inventory."""

from __future__ import annotations

import shlex
import subprocess
from dataclasses import dataclass

from ...errors import CcrpError

IPTABLES = ["iptables", "-w", "10"]  # -w: wait for the xtables lock libvirtd and dockerd also take


def comment(fleet: str, robot: str = "") -> str:
    return f"ccrp:{fleet}:{robot}"


@dataclass(frozen=True)
class Forward:
    """One clone's VPN port, forwarded from `address`:`port` of the libvirt host."""

    fleet: str
    robot: str
    address: str
    port: int
    clone_ip: str
    vpn_port: int
    proto: str  # udp or tcp, the inventory's vpn.proto

    def __str__(self) -> str:
        return f"{self.proto} {self.address}:{self.port} -> {self.clone_ip}:{self.vpn_port}"

    @property
    def endpoint(self) -> str:
        return f"{self.address}:{self.port}"

    def rules(self) -> list[tuple[str, list[str]]]:
        """(table, chain and match) of each rule, as `iptables -A` takes them."""
        note = ["-m", "comment", "--comment", comment(self.fleet, self.robot)]
        return [
            ("nat", ["PREROUTING", "-d", f"{self.address}/32", "-p", self.proto, "-m", self.proto, "--dport", str(self.port),
                     *note, "-j", "DNAT", "--to-destination", f"{self.clone_ip}:{self.vpn_port}"]),
            ("filter", ["FORWARD", "-d", f"{self.clone_ip}/32", "-p", self.proto, "-m", self.proto, "--dport", str(self.vpn_port),
                        "-m", "conntrack", "--ctstate", "DNAT", *note, "-j", "ACCEPT"]),
        ]


def ensure(fw: Forward) -> bool:
    """Make the clone's rules, each first in its chain; True if one was missing. A rule of the robot
    that differs (its clone's address or port changed) goes first."""
    made = False
    wanted = {(table, tuple(spec)) for table, spec in fw.rules()}
    for table, spec in listed(fw.fleet, fw.robot):
        if (table, tuple(spec)) not in wanted:
            _iptables(table, "-D", *spec)
    for table, spec in fw.rules():
        if _iptables(table, "-C", *spec, check=False) != 0:
            _iptables(table, "-I", spec[0], "1", *spec[1:])
            made = True
    return made


def listed(fleet: str, robot: str | None = None) -> list[tuple[str, list[str]]]:
    """The fleet's rules (of one robot, with `robot`) as they are: (table, chain and match)."""
    found = []
    for table, chain in (("nat", "PREROUTING"), ("filter", "FORWARD")):
        for line in _output(table, "-S", chain).splitlines():
            tokens = shlex.split(line)  # iptables quotes the comment, as a shell would read it
            if tokens[:1] != ["-A"] or "--comment" not in tokens:
                continue
            note = tokens[tokens.index("--comment") + 1]
            if note == comment(fleet, robot or "") or (robot is None and note.startswith(comment(fleet))):
                found.append((table, tokens[1:]))
    return found


def robot_of(spec: list[str]) -> str:
    return spec[spec.index("--comment") + 1].rpartition(":")[2]


def remove(fleet: str, robot: str | None = None) -> int:
    """Delete the fleet's rules (one robot's, with `robot`); how many there were."""
    rules = listed(fleet, robot)
    for table, spec in rules:
        _iptables(table, "-D", *spec)
    return len(rules)


def _iptables(table: str, *args: str, check: bool = True) -> int:
    proc = _run([*IPTABLES, "-t", table, *args])
    if check and proc.returncode != 0:
        raise CcrpError(f"`iptables -t {table} {' '.join(args[:2])} ...` failed: {' '.join(proc.stderr.split())[-200:]}",
                        hint="provider.vpn_forward needs root on the libvirt host (iptables)")
    return proc.returncode


def _output(table: str, *args: str) -> str:
    proc = _run([*IPTABLES, "-t", table, *args])
    if proc.returncode != 0:
        raise CcrpError(f"cannot list iptables table {table}: {' '.join(proc.stderr.split())[-200:]}",
                        hint="provider.vpn_forward needs root on the libvirt host (iptables)")
    return proc.stdout


def _run(argv: list[str]) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(argv, capture_output=True, text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise CcrpError(f"cannot run iptables: {exc}", hint="install iptables (Debian: apt-get install iptables)") from None
