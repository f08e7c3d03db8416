"""End to end: the entry gateway's rules (render/gateway.py) carry a robot's real OpenVPN tunnel to its
clone, and nothing else.

Three network namespaces made for this module stand for the places of a cloud fleet: "robot" on the
internet (198.51.100.0/24, a documentation range), "gateway" with one leg there and one on the
fleet's common network, and "clone" on the common network only, at nao1's common address. The
gateway namespace loads the rules ccrp renders for the gateway instance with iptables-restore, as
its unit does. The clone has no route to the internet, so its replies reach the robot only because
the gateway translates both ways. nao1's clone runs the OpenVPN server ccrp renders; the robot dials
the gateway's public address at nao1's port from its bundle.
"""

from __future__ import annotations

import os
import shutil
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from ccrp_cli.models.addressing import entry_port, gateway_ip
from ccrp_cli.render import gateway
from ccrp_cli.render.bundles import edge_bundle, write_bundle
from tests.e2e.vpnlab import COMPLETED, NEEDS, Lab, OpenVPNProcess, build_fleet, ping, serve_clone, sh, wait_for

LAB = Path(__file__).resolve().parents[2] / "inventories" / "lab.yaml"

pytestmark = [*NEEDS, pytest.mark.skipif(shutil.which("iptables-restore") is None, reason="iptables is not installed")]

NS = {place: f"ccrp-e2e-{place}-gw-{os.getpid()}" for place in ("robot", "gateway", "clone")}
PUBLIC_NET, GATEWAY_PUBLIC, ROBOT_PUBLIC = "198.51.100.0/24", "198.51.100.1", "198.51.100.2"
OPERATOR = "203.0.113.0/24"  # the operator's range: not the robot's


def in_ns(place: str, *argv: str, check: bool = True):
    return sh("ip", "netns", "exec", NS[place], *argv, check=check)


# One TCP connection attempt from a namespace: "open", "refused" (something answered with a reset)
# or "silent" (the packets were dropped).
TCP_TRY = r"""
import socket, sys
s = socket.socket()
s.settimeout(2)
try:
    s.connect((sys.argv[1], int(sys.argv[2])))
    print("open")
except ConnectionRefusedError:
    print("refused")
except OSError:
    print("silent")
"""


def tcp_try(place: str, host: str, port: int) -> str:
    return in_ns(place, sys.executable, "-c", TCP_TRY, host, str(port)).stdout.strip()


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Lab:
    return build_fleet(LAB, tmp_path_factory.mktemp("ccrp-home"), ("nao1", "nao2"))


@pytest.fixture(scope="module")
def places(lab: Lab) -> Iterator[None]:
    """robot -- gateway -- clone, the gateway's rules loaded (nao1 and nao2 forwarded)."""
    inv = lab.fleet.inventory
    common = inv.common.cidr
    try:
        for ns in NS.values():
            sh("ip", "netns", "add", ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        sh("ip", "-n", NS["robot"], "link", "add", "pub", "type", "veth", "peer", "name", "pub", "netns", NS["gateway"])
        sh("ip", "-n", NS["clone"], "link", "add", "common", "type", "veth", "peer", "name", "common", "netns", NS["gateway"])
        prefix = PUBLIC_NET.split("/")[1]
        for place, dev, addr in (("robot", "pub", f"{ROBOT_PUBLIC}/{prefix}"),
                                 ("gateway", "pub", f"{GATEWAY_PUBLIC}/{prefix}"),
                                 ("gateway", "common", f"{gateway_ip(inv)}/{common.prefixlen}"),
                                 ("clone", "common", f"{lab.views['nao1'].addr.common_ip}/{common.prefixlen}")):
            sh("ip", "-n", NS[place], "addr", "add", addr, "dev", dev)
            sh("ip", "-n", NS[place], "link", "set", dev, "up")
        rules = gateway.rules(inv, gateway.entries(inv, [v.addr for v in lab.views.values()]), OPERATOR)
        in_ns("gateway", "sysctl", "-q", "-w", "net.ipv4.ip_forward=1")
        restore = sh("sh", "-c", 'ip netns exec "$1" iptables-restore < "$2"', "-",
                     NS["gateway"], str(write_rules(lab, rules)), check=False)
        assert restore.returncode == 0, f"iptables-restore refused the gateway's rules: {restore.stderr}"
        assert wait_for(lambda: ping(NS["robot"], GATEWAY_PUBLIC), 5), "the public veth does not carry packets"
        yield
    finally:
        for ns in NS.values():
            sh("ip", "netns", "delete", ns, check=False)


def write_rules(lab: Lab, rules: str) -> Path:
    path = lab.fleet.store.root / "gateway.rules"
    path.write_text(rules)
    return path


@pytest.fixture(scope="module")
def clone(lab: Lab, places: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[OpenVPNProcess]:
    log = tmp_path_factory.mktemp("clone") / "server.log"
    with serve_clone(NS["clone"], lab.views["nao1"], lab.creds["nao1"], log) as (_dir, server):
        yield server


def dial(lab: Lab, tmp: Path, robot: str, port: int) -> OpenVPNProcess:
    """robot's client, from its bundle, dialling the gateway's public address at `port`."""
    bundle = write_bundle(tmp / f"edge-{robot}-{port}", edge_bundle(lab.views[robot], lab.creds[robot], f"{GATEWAY_PUBLIC}:{port}"),
                          {"kind": "edge", "fleet": lab.fleet.name, "robot": robot})
    return OpenVPNProcess.start(NS["robot"], tmp / f"client-{robot}-{port}.log", "--config", str(bundle / "robot.ovpn"),
                                "--auth-user-pass", str(bundle / "vpn-credentials"), "--hand-window", "4")


def test_the_robot_tunnels_to_its_clone_through_its_port(lab: Lab, clone: OpenVPNProcess, tmp_path: Path) -> None:
    inv, a = lab.fleet.inventory, lab.views["nao1"].addr
    assert not ping(NS["robot"], a.common_ip) and not ping(NS["clone"], ROBOT_PUBLIC), \
        "robot and clone must not reach each other but through the gateway's translation"
    client = dial(lab, tmp_path, "nao1", entry_port(inv, a.index))
    try:
        client.wait_completed()
        assert wait_for(lambda: ping(NS["robot"], a.clone_vpn_ip), 5), "the robot cannot ping its clone in the tunnel"
        assert ping(NS["clone"], a.robot_vpn_ip), "the clone cannot ping its robot in the tunnel"
        # The clone saw the robot at the gateway's common address: the gateway holds no key, it
        # passes the tunnel's packets, authenticated end to end by the clone (certificate + password).
        log = clone.text()
        assert f"MULTI: primary virtual IP for nao1/{gateway_ip(inv)}:" in log, log
        assert "Username/Password authentication succeeded for username 'nao1'" in log, log
    finally:
        client.stop()


def test_only_the_robots_ports_pass(lab: Lab, clone: OpenVPNProcess, tmp_path: Path) -> None:
    """nao2's port leads to nao2's clone (absent here), never to nao1's; the VPN port itself, and
    any other, lead nowhere; SSH is open to the operator's range only (the robot's gets silence)."""
    inv = lab.fleet.inventory
    since = clone.size()
    strays = [dial(lab, tmp_path, "nao1", port) for port in
              (entry_port(inv, lab.views["nao2"].addr.index), inv.vpn.port, entry_port(inv, 40))]
    try:
        assert not wait_for(lambda: any(COMPLETED in c.text() for c in strays), 8), "a tunnel came up on a port not nao1's"
        # A new peer's lines begin with its address (the gateway's); the end of the first test's
        # session, which may still be logged, begins with "nao1/".
        heard = [line for line in clone.text(since).splitlines() if line.startswith(f"{gateway_ip(inv)}:")]
        assert not heard, f"nao1's clone heard a port not nao1's:\n{clone.text(since)}"
    finally:
        for c in strays:
            c.stop()
    assert tcp_try("robot", GATEWAY_PUBLIC, 22) == "silent"
    assert tcp_try("clone", str(gateway_ip(inv)), 22) == "silent", "SSH from the common network is not the operator's"


def test_the_clone_goes_out_from_the_gateways_address(lab: Lab, places: None) -> None:
    """With its default route through the gateway (the cloud's route table), the clone reaches the
    internet and is seen there at the gateway's public address."""
    inv = lab.fleet.inventory
    in_ns("clone", "ip", "route", "add", "default", "via", str(gateway_ip(inv)))
    try:
        # A listener in the robot's namespace (the internet) prints who connected; the clone connects.
        echo = sh("sh", "-c", (
            'ip netns exec "$1" "$3" -c "$4" & sleep 0.5; ip netns exec "$2" "$3" -c "$5"; wait'),
            "-", NS["robot"], NS["clone"], sys.executable, SEEN_FROM, SAY_HELLO.replace("HOST", ROBOT_PUBLIC))
        assert echo.stdout.split() == [GATEWAY_PUBLIC], echo.stdout + echo.stderr
    finally:
        in_ns("clone", "ip", "route", "del", "default", check=False)


# In the robot namespace: accept one TCP connection on port 8080 and print the peer's address.
SEEN_FROM = r"""
import socket
s = socket.socket(); s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1); s.bind(("0.0.0.0", 8080)); s.listen(1)
s.settimeout(10)
conn, peer = s.accept(); print(peer[0]); conn.close()
"""
SAY_HELLO = r"""
import socket
socket.create_connection(("HOST", 8080), timeout=5).close()
"""
