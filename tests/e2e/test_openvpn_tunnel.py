"""End to end: a clone's OpenVPN server and its robot's client, both rendered by ccrp, run for real.

Two network namespaces made for this module ("clone" and "robot") are joined by a veth pair on
192.168.250.0/30; nothing touches the host's own interfaces. One server runs for the whole
module, laid out as a clone's /etc/openvpn/server/ccrp would be. The first test brings nao1's
tunnel up; the others show the server refusing clients that must not get in (docs/security.md).
"""

from __future__ import annotations

import os
import re
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml
from cryptography import x509

from ccrp_cli.ops import vpn
from ccrp_cli.pki.store import RobotCredentials
from ccrp_cli.render import openvpn
from ccrp_cli.render.bundles import clone_secrets, edge_bundle, write_bundle
from ccrp_cli.render.view import CloneView
from tests.e2e.vpnlab import (
    COMPLETED, NEEDS, Lab, OpenVPNProcess, build_fleet, ping, serve_clone, sh, wait_for,
)
LAB = Path(__file__).resolve().parents[2] / "inventories" / "lab.yaml"

pytestmark = NEEDS

# Unique per run, so that parallel runs on one host never meet.
NS_CLONE = f"ccrp-e2e-clone-{os.getpid()}"
NS_ROBOT = f"ccrp-e2e-robot-{os.getpid()}"
CLONE_OUTER_IP, ROBOT_OUTER_IP, OUTER_PREFIX = "192.168.250.1", "192.168.250.2", 30

REFUSAL_WINDOW = 15.0  # a refused client must not get a tunnel in this time
# When the server refuses a certificate, the client hears nothing back and would wait out its
# 60 s hand-window before giving up on the attempt. Refused clients get a short one, so that the
# attempt visibly ends; this changes when a client gives up, never what it accepts.
GIVE_UP_SOON = ("--hand-window", "4")
# The client gave up on an attempt: it restarts (TLS errors) or exits (AUTH_FAILED).
ATTEMPT_ENDED = re.compile(r"SIGUSR1\[soft,|SIGTERM\[soft,auth-failure\]|AUTH_FAILED")


# -- helpers ---------------------------------------------------------------------------------


def write_edge_bundle(out: Path, view: CloneView, creds: RobotCredentials) -> Path:
    """The robot's edge bundle, pointing at the clone's end of the veth pair."""
    files = edge_bundle(view, creds, remote=CLONE_OUTER_IP)
    return write_bundle(out, files, {"kind": "edge", "fleet": view.fleet, "robot": view.name})


def write_credentials(path: Path, user: str, password: str) -> Path:
    path.write_text(f"{user}\n{password}\n")
    path.chmod(0o600)
    return path


def replace_file(src: Path, dest: Path) -> None:
    """Swap `dest` for a copy of `src` in one rename, as the transport pushes files."""
    tmp = dest.with_name(f".{dest.name}.tmp")
    shutil.copyfile(src, tmp)
    tmp.chmod(0o644)
    os.replace(tmp, dest)


# -- fixtures --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Lab:
    return build_fleet(LAB, tmp_path_factory.mktemp("ccrp-home"), ("nao1", "nao2"))


@pytest.fixture(scope="module")
def namespaces() -> Iterator[None]:
    """The clone and robot namespaces and a veth pair between them, created inside them."""
    try:
        for ns in (NS_CLONE, NS_ROBOT):
            sh("ip", "netns", "add", ns)
            sh("ip", "-n", ns, "link", "set", "lo", "up")
        sh("ip", "-n", NS_CLONE, "link", "add", "veth0", "type", "veth", "peer", "name", "veth0", "netns", NS_ROBOT)
        for ns, ip in ((NS_CLONE, CLONE_OUTER_IP), (NS_ROBOT, ROBOT_OUTER_IP)):
            sh("ip", "-n", ns, "addr", "add", f"{ip}/{OUTER_PREFIX}", "dev", "veth0")
            sh("ip", "-n", ns, "link", "set", "veth0", "up")
        assert wait_for(lambda: ping(NS_ROBOT, CLONE_OUTER_IP), 5), "the veth pair does not carry packets"
        yield
    finally:
        for ns in (NS_CLONE, NS_ROBOT):
            sh("ip", "netns", "delete", ns, check=False)


@dataclass
class Clone:
    dir: Path
    server: OpenVPNProcess
    view: CloneView


@pytest.fixture(scope="module")
def clone(lab: Lab, namespaces: None, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Clone]:
    """nao1's clone: its VPN directory laid out as on the clone, and openvpn serving from it."""
    view, creds = lab.views["nao1"], lab.creds["nao1"]
    log = tmp_path_factory.mktemp("clone") / "server.log"
    with serve_clone(NS_CLONE, view, creds, log) as (vpn_dir, server):
        served = Clone(vpn_dir, server, view)
        try:
            yield served
        finally:
            served.server.stop()  # serve() restarts it: serve_clone stops only the first one


@dataclass
class Robot:
    """Starts robot-side clients in the robot namespace; all are stopped after the test."""

    tmp: Path
    clients: list[OpenVPNProcess] = field(default_factory=list)

    def connect(self, bundle: Path, credentials: Path | None = None, *extra: str) -> OpenVPNProcess:
        # The profile reads /etc/ccrp/vpn-credentials, where install.sh puts the bundle's file;
        # a later --auth-user-pass overrides it with the file in the bundle itself.
        creds = credentials or bundle / "vpn-credentials"
        log = self.tmp / f"client-{len(self.clients)}.log"
        client = OpenVPNProcess.start(
            NS_ROBOT, log, "--config", str(bundle / "robot.ovpn"), "--auth-user-pass", str(creds), *extra
        )
        self.clients.append(client)
        return client


@pytest.fixture
def robot(clone: Clone, tmp_path: Path) -> Iterator[Robot]:
    r = Robot(tmp_path)
    try:
        yield r
    finally:
        for client in r.clients:
            client.stop()


def assert_refused(client: OpenVPNProcess, clone: Clone, since: int, reason: str) -> None:
    """Within REFUSAL_WINDOW the server logs `reason` (after offset `since`) and the client's
    attempt ends, and the client never completes initialisation. Polls, so that it returns as
    soon as the attempt has ended."""
    pattern = re.compile(reason)
    wait_for(
        lambda: COMPLETED in client.text()
        or (pattern.search(clone.server.text(since)) and (ATTEMPT_ENDED.search(client.text()) or not client.running)),
        REFUSAL_WINDOW,
    )
    logs = f"--- client ---\n{client.text()}\n--- server ---\n{clone.server.text(since)}"
    assert COMPLETED not in client.text(), f"the client got a tunnel:\n{logs}"
    assert pattern.search(clone.server.text(since)), f"the server did not log {reason!r}:\n{logs}"
    assert ATTEMPT_ENDED.search(client.text()) or not client.running, f"the client's attempt did not end:\n{logs}"
    assert clone.server.running, f"the server died:\n{logs}"


# -- tests -----------------------------------------------------------------------------------


def test_tunnel_comes_up(lab: Lab, clone: Clone, robot: Robot) -> None:
    a = clone.view.addr
    bundle = write_edge_bundle(robot.tmp / "edge", lab.views["nao1"], lab.creds["nao1"])
    client = robot.connect(bundle)
    client.wait_completed()

    addrs = sh("ip", "-n", NS_ROBOT, "-4", "-o", "addr", "show", "dev", "ccrpvpn").stdout
    assert f"inet {a.robot_vpn_ip}/{a.vpn_subnet.prefixlen}" in addrs
    assert wait_for(lambda: ping(NS_ROBOT, a.clone_vpn_ip), 5), "the robot cannot ping its clone"
    assert ping(NS_CLONE, a.robot_vpn_ip), "the clone cannot ping its robot"
    # The second factor was checked (by ccrp-auth, as nobody), and the server knows the peer as nao1.
    log = clone.server.text()
    assert "Username/Password authentication succeeded for username 'nao1'" in log, log
    assert f"MULTI: primary virtual IP for nao1/{ROBOT_OUTER_IP}:" in log, log


@dataclass
class Refusal:
    """A client the clone must refuse, and what the server is expected to log about it."""

    bundle: Path
    reason: str  # a regular expression
    credentials: Path | None = None  # None: the bundle's own vpn-credentials


def cert_serial(pem: str) -> int:
    return x509.load_pem_x509_certificate(pem.encode()).serial_number


def with_client_cert(creds: RobotCredentials, other: RobotCredentials) -> RobotCredentials:
    """`creds` (CA, tls-crypt key, password) but presenting `other`'s client certificate."""
    return creds.model_copy(update={"client_cert_pem": other.client_cert_pem, "client_key_pem": other.client_key_pem})


def wrong_password(lab: Lab, tmp: Path) -> Refusal:
    """nao1's genuine bundle with a wrong password: the certificate alone is not enough."""
    bundle = write_edge_bundle(tmp / "edge", lab.views["nao1"], lab.creds["nao1"])
    wrong = write_credentials(tmp / "wrong-credentials", "nao1", "not-" + lab.creds["nao1"].password)
    return Refusal(bundle, r"TLS Auth Error: Auth Username/Password verification failed for peer", wrong)


def foreign_ca(fleet_name: str) -> Callable[[Lab, Path], Refusal]:
    """nao1's bundle, but with a client certificate for nao1 from another fleet's CA.

    The client keeps the real CA (so it accepts the clone), the clone's tls-crypt key (so its
    packets get through) and the right password: only the server's certificate check can refuse it.
    """

    def build(lab: Lab, tmp: Path) -> Refusal:
        inventory = yaml.safe_load(LAB.read_text()) | {"fleet": fleet_name}
        (tmp / "other.yaml").write_text(yaml.safe_dump(inventory))
        other = build_fleet(tmp / "other.yaml", tmp / "other-home", ("nao1",)).creds["nao1"]
        assert other.ca_pem != lab.creds["nao1"].ca_pem
        bundle = write_edge_bundle(tmp / "edge", lab.views["nao1"], with_client_cert(lab.creds["nao1"], other))
        serial = cert_serial(other.client_cert_pem)
        reason = rf"VERIFY ERROR: depth=0, error=unable to get local issuer certificate: CN=nao1, serial={serial}\b"
        return Refusal(bundle, reason)

    return build


def wrong_robot(lab: Lab, tmp: Path) -> Refusal:
    """nao2's certificate (valid in this fleet) offered to nao1's clone, with nao1's profile,
    tls-crypt key and password: the tls-verify check (ccrp-auth: the CN must be one of the clone's
    names) is what tells the two robots apart, before any password is asked."""
    creds = with_client_cert(lab.creds["nao1"], lab.creds["nao2"])
    bundle = write_edge_bundle(tmp / "edge", lab.views["nao1"], creds)
    return Refusal(bundle, r"VERIFY SCRIPT ERROR: depth=0, CN=nao2\b")


@pytest.mark.parametrize(
    "case",
    [
        pytest.param(wrong_password, id="wrong-password"),
        pytest.param(foreign_ca("rogue"), id="other-fleet-ca"),
        # Same fleet name, hence a CA of the same name ("ccrp lab CA"), but another key.
        pytest.param(foreign_ca("lab"), id="lookalike-ca"),
        pytest.param(wrong_robot, id="wrong-robot-cert"),
    ],
)
def test_refused(lab: Lab, clone: Clone, robot: Robot, case: Callable[[Lab, Path], Refusal]) -> None:
    refusal = case(lab, robot.tmp)
    since = clone.server.size()
    client = robot.connect(refusal.bundle, refusal.credentials, *GIVE_UP_SOON)
    assert_refused(client, clone, since, refusal.reason)


def test_revoked_cert_refused(lab: Lab, clone: Clone, robot: Robot) -> None:
    # Rendered while nao1's certificate was still valid, as on a robot that is then revoked.
    bundle = write_edge_bundle(robot.tmp / "edge", lab.views["nao1"], lab.creds["nao1"])
    served_crl = clone.dir / "keys" / "crl.pem"
    original = robot.tmp / "crl.before.pem"
    shutil.copyfile(served_crl, original)
    try:
        (revoked,) = vpn.revoke(lab.fleet, "nao1")
        # Push the new CRL to the clone; openvpn re-reads it on the next TLS session.
        replace_file(lab.fleet.pki.crl_path, served_crl)
        since = clone.server.size()
        client = robot.connect(bundle, None, *GIVE_UP_SOON)
        serial = int(revoked["serial"], 16)
        assert revoked["revoked"] and serial == cert_serial(lab.creds["nao1"].client_cert_pem)
        reason = rf"VERIFY ERROR: depth=0, error=certificate revoked: CN=nao1, serial={serial}\b"
        assert_refused(client, clone, since, reason)
    finally:
        # The server keeps running for the other tests: hand it back the CRL it started with.
        replace_file(original, served_crl)


def serve(clone: Clone, creds: RobotCredentials, log: Path, *extra: str) -> None:
    """(Re)start the clone's server with `creds` pushed, as `fleet up` does after a change."""
    clone.server.stop()
    write_bundle(clone.dir / "keys", clone_secrets(clone.view, creds), {"kind": "clone-secrets", "robot": clone.view.name})
    os.chown(clone.dir / "keys" / "passwd", 0, 65534)
    clone.server = OpenVPNProcess.start(NS_CLONE, log, "--cd", str(clone.dir), "--config", "server.conf", *extra)
    clone.server.wait_completed()


def test_after_renew_each_old_credential_fails_alone(lab: Lab, clone: Clone, robot: Robot) -> None:
    """`vpn issue-cert --renew` replaces the certificate, the password and the tls-crypt key: a
    client holding the new set with any single one of the old parts is refused."""
    old = lab.creds["nao1"]
    vpn.issue(lab.fleet, "nao1", renew=True)
    new = lab.fleet.pki.credentials("nao1")
    assert (new.password, new.tls_crypt_key) != (old.password, old.tls_crypt_key)
    try:
        serve(clone, new, robot.tmp / "server-renewed.log")
        fresh = robot.connect(write_edge_bundle(robot.tmp / "new", lab.views["nao1"], new))
        fresh.wait_completed()  # control: the new set gets a tunnel from this very server
        fresh.stop()

        serial = cert_serial(old.client_cert_pem)
        cases = {
            "old certificate": (with_client_cert(new, old), None,
                                rf"VERIFY ERROR: depth=0, error=certificate revoked: CN=nao1, serial={serial}\b"),
            "old password": (new, write_credentials(robot.tmp / "old-password.txt", "nao1", old.password),
                             r"Auth Username/Password verification failed for peer"),
            "old tls-crypt key": (new.model_copy(update={"tls_crypt_key": old.tls_crypt_key}), None,
                                  r"tls-crypt unwrapping failed"),
        }
        for name, (creds, password_file, reason) in cases.items():
            since = clone.server.size()
            client = robot.connect(write_edge_bundle(robot.tmp / name.replace(" ", "-"), lab.views["nao1"], creds),
                                   password_file, *GIVE_UP_SOON)
            assert_refused(client, clone, since, reason)
            client.stop()
    finally:
        serve(clone, old, robot.tmp / "server-restored.log")  # the module's server as it started


def test_the_power_device_connects_as_itself_beside_its_robot(lab: Lab, clone: Clone, robot: Robot) -> None:
    """The robot's power device (`robot power bundle`): its own certificate (CN nao1.power) and
    password, admitted by the clone once its passwd names it, at its own fixed address, while the
    robot's own session stays up."""
    from ccrp_cli.render.bundles import power_bundle

    a, view = clone.view.addr, lab.views["nao1"]
    old = lab.creds["nao1"]
    v = lab.fleet.inventory.vpn
    lab.fleet.pki.issue_power("nao1", v.cert_days, v.crl_days)
    new = lab.fleet.pki.credentials("nao1")
    (clone.dir / "ccd" / "nao1.power").write_text(openvpn.device_ccd_entry(view))
    try:
        serve(clone, new, robot.tmp / "server-device.log")
        robot_client = robot.connect(write_edge_bundle(robot.tmp / "edge", view, new))
        device_dir = write_bundle(robot.tmp / "power", power_bundle(view, new, remote=CLONE_OUTER_IP), {"kind": "power"})
        device = OpenVPNProcess.start(NS_ROBOT, robot.tmp / "device.log", "--config", str(device_dir / "power.ovpn"),
                                      "--auth-user-pass", str(device_dir / "power-credentials"))
        robot.clients.append(device)
        robot_client.wait_completed()
        device.wait_completed()
        addrs = sh("ip", "-n", NS_ROBOT, "-4", "-o", "addr", "show", "dev", "ccrppwr").stdout
        assert f"inet {a.device_vpn_ip}/{a.vpn_subnet.prefixlen}" in addrs
        log = clone.server.text()
        assert "Username/Password authentication succeeded for username 'nao1.power'" in log, log
        assert "MULTI: primary virtual IP for nao1.power/" in log and "MULTI: primary virtual IP for nao1/" in log, log
        assert robot_client.running and COMPLETED in robot_client.text()  # the robot's session stays
        # The robot's password with the device's certificate: refused.
        since = clone.server.size()
        wrong = write_credentials(robot.tmp / "robot-password.txt", "nao1.power", new.password)
        refused = OpenVPNProcess.start(NS_ROBOT, robot.tmp / "device-wrong.log", "--config", str(device_dir / "power.ovpn"),
                                       "--auth-user-pass", str(wrong), "--dev", "ccrppw2", *GIVE_UP_SOON)
        robot.clients.append(refused)
        assert_refused(refused, clone, since, r"Auth Username/Password verification failed for peer")
    finally:
        serve(clone, old, robot.tmp / "server-restored.log")  # the module's server as it started


def test_a_revoked_session_that_escaped_the_kill_ends_at_renegotiation(lab: Lab, clone: Clone, robot: Robot) -> None:
    """Without `vpn revoke`'s kill, the server's renegotiation (reneg-sec) fails for a revoked
    certificate, and tran-window bounds how long the old data-channel key lives after that: the
    session ends within reneg-sec + tran-window. Run with both shortened (10 s each) here; the
    rendered config has 300 s and 60 s."""
    conf = (clone.dir / "server.conf").read_text()
    assert "\nreneg-sec 300\n" in conf and "\ntran-window 60\n" in conf
    a = clone.view.addr
    creds = lab.creds["nao1"]
    fast = ("--reneg-sec", "10", "--tran-window", "10")
    served_crl = clone.dir / "keys" / "crl.pem"
    try:
        serve(clone, creds, robot.tmp / "server-fast.log", *fast)
        client = robot.connect(write_edge_bundle(robot.tmp / "edge", lab.views["nao1"], creds))
        client.wait_completed()
        assert wait_for(lambda: ping(NS_ROBOT, a.clone_vpn_ip), 5)
        # Revoked, the new CRL on the clone, and no kill.
        revoked = vpn.revoke(lab.fleet, "nao1") if lab.fleet.pki.revoked_since("nao1") is None else None
        replace_file(lab.fleet.pki.crl_path, served_crl)
        t0 = time.monotonic()
        assert wait_for(lambda: not ping(NS_ROBOT, a.clone_vpn_ip), 40, interval=1), \
            f"the revoked session still carries traffic after 40 s:\n{clone.server.text()[-3000:]}"
        took = time.monotonic() - t0
        print(f"the revoked session ended {took:.1f} s after the CRL reached the server (reneg-sec 10, tran-window 10)")
        assert took <= 10 + 10 + 10, took
        assert "certificate revoked" in clone.server.text(), clone.server.text()[-2000:]
        assert revoked is None or revoked[0]["revoked"]
    finally:
        serve(clone, lab.creds["nao1"], robot.tmp / "server-restored.log")
