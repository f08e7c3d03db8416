"""What the OpenVPN end-to-end tests share: commands in network namespaces, openvpn processes
with their logs, a fleet with issued robots, and a clone's OpenVPN server laid out as on a clone."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.ops import vpn
from ccrp_cli.pki.store import RobotCredentials
from ccrp_cli.render import openvpn
from ccrp_cli.render.bundles import clone_secrets, write_bundle
from ccrp_cli.render.view import CloneView
from ccrp_cli.templates import static

OPENVPN = "/usr/sbin/openvpn"
START_TIMEOUT = 20.0  # the server or a good client reaching "Initialization Sequence Completed"
COMPLETED = "Initialization Sequence Completed"


def sh(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(args, capture_output=True, text=True)
    if check and result.returncode != 0:
        pytest.fail(f"`{' '.join(args)}` failed ({result.returncode}): {result.stderr.strip()}")
    return result


# An ICMP echo from inside a namespace, without depending on iputils-ping being installed.
# COUNT ICMP echoes, 10 ms apart, from inside a namespace (iputils-ping need not be installed): one
# round trip (ms) per echo answered within a second, as JSON.
PINGS = r"""
import json, os, socket, struct, sys, time

def checksum(b):
    s = sum(struct.unpack(f"!{len(b) // 2}H", b))
    s = (s >> 16) + (s & 0xFFFF)
    return ~(s + (s >> 16)) & 0xFFFF

target, count, ident, rtts = sys.argv[1], int(sys.argv[2]), os.getpid() & 0xFFFF, []
with socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_ICMP) as s:
    s.settimeout(1.0)
    for seq in range(count):
        header = struct.pack("!BBHHH", 8, 0, 0, ident, seq)
        packet = struct.pack("!BBHHH", 8, 0, checksum(header + b"ccrp-bench"), ident, seq) + b"ccrp-bench"
        t0 = time.perf_counter()
        s.sendto(packet, (target, 0))
        while True:
            try:
                data, (source, _) = s.recvfrom(2048)
            except TimeoutError:
                break
            ihl = (data[0] & 0x0F) * 4
            kind, _, _, rid, rseq = struct.unpack("!BBHHH", data[ihl:ihl + 8])
            if source == target and kind == 0 and rid == ident and rseq == seq:
                rtts.append((time.perf_counter() - t0) * 1000)
                break
        time.sleep(0.01)
print(json.dumps(rtts))
"""


def ping(netns: str, ip: object) -> bool:
    """One ICMP echo from `netns` to `ip`, answered within a second."""
    out = sh("ip", "netns", "exec", netns, sys.executable, "-c", PINGS, str(ip), "1", check=False).stdout
    return out.strip() not in ("", "[]")


# What a module of these tests needs of this machine.
NEEDS = [
    pytest.mark.slow,
    pytest.mark.root,
    pytest.mark.skipif(os.geteuid() != 0, reason="needs root for network namespaces and tun devices"),
    pytest.mark.skipif(not os.access(OPENVPN, os.X_OK), reason=f"{OPENVPN} is not installed"),
    pytest.mark.skipif(not os.path.exists("/dev/net/tun"), reason="/dev/net/tun is missing (no tun support)"),
    pytest.mark.skipif(shutil.which("ip") is None, reason="iproute2 (`ip`) is not installed"),
]


def wait_for(predicate: Callable[[], object], timeout: float, interval: float = 0.1) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())


@dataclass
class OpenVPNProcess:
    """openvpn running in a namespace, its stdout and stderr in `log`."""

    proc: subprocess.Popen[bytes]
    log: Path

    @classmethod
    def start(cls, netns: str, log: Path, *args: str) -> "OpenVPNProcess":
        with log.open("wb") as out:
            proc = subprocess.Popen(
                ["ip", "netns", "exec", netns, OPENVPN, "--suppress-timestamps", *args],
                stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
            )
        return cls(proc, log)

    def size(self) -> int:
        return self.log.stat().st_size

    def text(self, since: int = 0) -> str:
        return self.log.read_bytes()[since:].decode(errors="replace")

    @property
    def running(self) -> bool:
        return self.proc.poll() is None

    def stop(self) -> None:
        if self.running:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)

    def wait_completed(self, timeout: float = START_TIMEOUT) -> None:
        ok = wait_for(lambda: COMPLETED in self.text() or not self.running, timeout)
        assert ok and COMPLETED in self.text(), f"openvpn did not come up:\n{self.text()}"


@dataclass
class Lab:
    """The lab fleet with nao1 and nao2 issued, and a view and the credentials of each."""

    fleet: Fleet
    views: dict[str, CloneView]
    creds: dict[str, RobotCredentials]


def build_fleet(inventory: Path, home: Path, robots: tuple[str, ...]) -> Lab:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CCRP_HOME", str(home))
        fleet = Fleet.open(inventory)
        vpn.init(fleet)
        for robot in robots:
            vpn.issue(fleet, robot)
        state = fleet.store.load_state()
        views = {r: clone_view(fleet, state, r) for r in robots}
        creds = {r: fleet.pki.credentials(r) for r in robots}
    return Lab(fleet, views, creds)



@contextmanager
def serve_clone(netns: str, view: CloneView, creds: RobotCredentials, log: Path, *extra: str) -> Iterator[tuple[Path, OpenVPNProcess]]:
    """The robot's clone in `netns`: its VPN directory laid out as on the clone, and openvpn serving
    from it until the block ends. Yields (the directory, the server)."""
    # Under /tmp and 0755: openvpn re-reads ccd/, crl.pem and runs ccrp-auth as nobody, who
    # cannot traverse pytest's 0700 tmp_path.
    vpn_dir = Path(tempfile.mkdtemp(prefix="ccrp-e2e-vpn-", dir="/tmp"))
    server: OpenVPNProcess | None = None
    try:
        vpn_dir.chmod(0o755)
        write_bundle(vpn_dir / "keys", clone_secrets(view, creds), {"kind": "clone-secrets", "robot": view.name})
        (vpn_dir / "keys").chmod(0o755)
        os.chown(vpn_dir / "keys" / "passwd", 0, 65534)  # root:nogroup 0640, as root:openvpn on the clone
        (vpn_dir / "server.conf").write_text(openvpn.server_conf(view, user="nobody", group="nogroup"))
        (vpn_dir / "ccd").mkdir(mode=0o755)
        (vpn_dir / "ccd" / view.name).write_text(openvpn.ccd_entry(view))
        (vpn_dir / "ccrp-auth").write_text(static("clone/ccrp-auth"))
        (vpn_dir / "ccrp-auth").chmod(0o755)
        server = OpenVPNProcess.start(netns, log, "--cd", str(vpn_dir), "--config", "server.conf", *extra)
        server.wait_completed()
        yield vpn_dir, server
    finally:
        if server is not None:
            server.stop()
        shutil.rmtree(vpn_dir, ignore_errors=True)
