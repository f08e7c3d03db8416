"""The relay agent's Zenoh config, run for real on loopback: mutual TLS against the relay CA, and
access control that admits only the CNs relay.json names (docs/security.md, Revocation)."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

from ccrp_cli.ops import vpn  # noqa: E402
from ccrp_cli.fleet import Fleet  # noqa: E402
from tests.conftest import LAB  # noqa: E402

from tests.unit.helpers import load_agent  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def fleet(ccrp_home):
    fleet = Fleet.open(LAB)
    vpn.init(fleet)
    for robot in ("nao1", "nao2"):
        vpn.issue(fleet, robot)
        fleet.pki.issue_relay(robot, "127.0.0.1", 30)
    return fleet


def files(fleet: Fleet, tmp: Path, profile: str, robot: str) -> dict:
    """TLS files of `robot`'s current certificate of `profile`, as relay.json names them."""
    index = fleet.pki.load_index()
    rec = fleet.pki.current_of(index, profile, robot)
    root = fleet.pki.root
    return {"ca": str(fleet.pki.relay_ca_path), "cert": str(root / rec.cert_path), "key": str(root / rec.key_path)}


def received(agent, listener: dict, dialler_tls: dict, seconds: float = 2.0) -> int:
    """Open the listener's session as the agent would; dial it with `dialler_tls` (admitted by
    the listener or not) and count the puts the listener's subscriber gets."""
    got: list = []
    session = zenoh.open(agent.zenoh_config(listener))
    try:
        session.declare_subscriber("ccrp/lab/**", lambda sample: got.append(sample))
        dialler = {"id": "c" + "1" * 23, "listen": "tls/127.0.0.1:0", "fleet": "lab", "tls": dialler_tls,
                   "peers": {"nao1": {"endpoint": listener["listen"], "cn": "relay-nao1-1"}}}
        other = zenoh.open(agent.zenoh_config(dialler))
        try:
            time.sleep(seconds)
            for _ in range(5):
                other.put("ccrp/lab/nao2/faces", b"x")
                time.sleep(0.05)
            time.sleep(0.5)
        finally:
            other.close()
    finally:
        session.close()
    return len(got)


def test_only_current_partner_certificates_get_data_through(fleet, tmp_path):
    agent = load_agent()
    def listener(admit: list[str]) -> dict:
        return {"id": "c" + "2" * 23, "fleet": "lab", "listen": f"tls/127.0.0.1:{free_port()}",
                "tls": files(fleet, tmp_path, "relay", "nao1"),
                "peers": {f"p{i}": {"endpoint": "tls/127.0.0.1:9", "cn": cn} for i, cn in enumerate(admit)}}

    nao2_relay = files(fleet, tmp_path, "relay", "nao2")
    assert received(agent, listener(["relay-nao2-1"]), nao2_relay) == 5  # control: admitted partner
    assert received(agent, listener([]), nao2_relay) == 0  # no partner: nobody gets through
    fleet.pki.issue_relay("nao2", "127.0.0.2", 30)  # nao2's clone moved: relay-nao2-2 replaces -1
    assert received(agent, listener(["relay-nao2-2"]), nao2_relay) == 0  # the replaced certificate
    robot = files(fleet, tmp_path, "client", "nao2") | {"ca": str(fleet.pki.relay_ca_path)}
    assert received(agent, listener(["nao2", "relay-nao2-2"]), robot) == 0  # a robot's VPN certificate
