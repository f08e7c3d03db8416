"""The fleet PKI, checked with the openssl command line as the oracle."""

from __future__ import annotations

import datetime as dt
import os
import shutil
import subprocess

import pytest
from cryptography import x509

from ccrp_cli.ops import vpn
from ccrp_cli.fleet import Fleet
from ccrp_cli.pki.secrets import hash_password, tls_crypt_key, verify_password
from tests.conftest import LAB, ROOT
from tests.unit.helpers import openssl_verify

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")


def certs(lab):
    return {r["cn"]: r for r in vpn.list_certs(lab)}


def test_openssl_accepts_every_issued_cert(lab):
    pki = lab.pki.root
    recs = certs(lab)
    assert set(recs) == {"ccrp lab CA", "nao1", "cri-nao1", "nao2", "cri-nao2", "turtlebot1", "cri-turtlebot1"}
    for rec in recs.values():
        proc = openssl_verify(pki, rec["path"], crl_check=True)
        assert proc.returncode == 0, proc.stdout + proc.stderr


def test_revoked_cert_is_rejected_with_crl_check_others_pass(lab):
    before = certs(lab)
    revoked = vpn.revoke(lab, "nao2")
    assert [r["cn"] for r in revoked] == ["nao2"] and revoked[0]["revoked"]
    pki = lab.pki.root
    bad = openssl_verify(pki, before["nao2"]["path"], crl_check=True)
    assert bad.returncode != 0 and "certificate revoked" in bad.stdout + bad.stderr
    for cn in ("nao1", "cri-nao1", "cri-nao2", "turtlebot1"):
        assert openssl_verify(pki, before[cn]["path"], crl_check=True).returncode == 0
    # Without -crl_check the signature is still fine: the CRL is what refuses it.
    assert openssl_verify(pki, before["nao2"]["path"]).returncode == 0
    # A new certificate for the robot is issued on request and is valid again.
    again = {r["profile"]: r for r in vpn.issue(lab, "nao2")}
    assert again["client"]["issued"] and not again["server"]["issued"]
    assert openssl_verify(pki, again["client"]["path"], crl_check=True).returncode == 0


def test_profiles_eku_and_usage(lab):
    recs = certs(lab)
    def load(cn):
        return x509.load_pem_x509_certificate(open(recs[cn]["path"], "rb").read())
    server, client, ca = load("cri-nao1"), load("nao1"), load("ccrp lab CA")
    eku = lambda c: list(c.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value)  # noqa: E731
    assert eku(server) == [x509.oid.ExtendedKeyUsageOID.SERVER_AUTH]
    assert eku(client) == [x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH]
    bc = ca.extensions.get_extension_for_class(x509.BasicConstraints)
    assert bc.critical and bc.value.ca
    ku = ca.extensions.get_extension_for_class(x509.KeyUsage).value
    assert ku.key_cert_sign and ku.crl_sign
    san = server.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert san.get_values_for_type(x509.DNSName) == ["cri-nao1"]
    # openssl's own purpose checks, as OpenVPN's remote-cert-tls relies on them
    text = subprocess.run(["openssl", "x509", "-in", recs["cri-nao1"]["path"], "-noout", "-purpose"],
                          capture_output=True, text=True).stdout
    assert "SSL server : Yes" in text
    text = subprocess.run(["openssl", "x509", "-in", recs["nao1"]["path"], "-noout", "-purpose"],
                          capture_output=True, text=True).stdout
    assert "SSL client : Yes" in text and "SSL server : No" in text


def test_serials_are_random_and_large(lab):
    serials = [int(r["serial"], 16) for r in vpn.list_certs(lab)]
    assert len(set(serials)) == len(serials)
    assert max(s.bit_length() for s in serials) > 100


def test_crl_number_and_lifetime(lab):
    crl = x509.load_pem_x509_crl(lab.pki.crl_path.read_bytes())
    first = crl.extensions.get_extension_for_class(x509.CRLNumber).value.crl_number
    assert crl.next_update_utc - dt.datetime.now(dt.timezone.utc) > dt.timedelta(days=365)
    vpn.revoke(lab, "nao1")
    crl2 = x509.load_pem_x509_crl(lab.pki.crl_path.read_bytes())
    assert crl2.extensions.get_extension_for_class(x509.CRLNumber).value.crl_number == first + 1
    out = subprocess.run(["openssl", "crl", "-in", str(lab.pki.crl_path), "-noout", "-text"],
                         capture_output=True, text=True).stdout
    assert "X509v3 CRL Number" in out


def test_init_and_issue_are_idempotent(lab):
    before = certs(lab)
    assert vpn.init(lab)["created"] is False
    again = vpn.issue(lab, "nao1")
    assert [r["issued"] for r in again] == [False, False]
    assert certs(lab) == before


def test_keys_are_0600_and_ca_key_never_leaves_private(lab):
    root = lab.pki.root
    for path in (root / "private").iterdir():
        assert oct(os.stat(path).st_mode & 0o777) == "0o600"
    assert oct(os.stat(root).st_mode & 0o777) == "0o700"


def test_rsa_fleet(ccrp_home, tmp_path):
    inv = tmp_path / "rsa.yaml"
    inv.write_text(LAB.read_text().replace("key_type: ecdsa-p256", "key_type: rsa3072"))
    fleet = Fleet.open(inv)
    vpn.init(fleet)
    rec = {r["profile"]: r for r in vpn.issue(fleet, "nao1")}
    cert = x509.load_pem_x509_certificate(open(rec["client"]["path"], "rb").read())
    assert cert.public_key().key_size == 3072
    assert openssl_verify(fleet.pki.root, rec["client"]["path"], crl_check=True).returncode == 0


def test_tls_crypt_key_format():
    key = tls_crypt_key()
    lines = key.splitlines()
    body = lines[lines.index("-----BEGIN OpenVPN Static key V1-----") + 1 : lines.index("-----END OpenVPN Static key V1-----")]
    assert len(body) == 16 and all(len(line) == 32 for line in body)
    assert len(bytes.fromhex("".join(body))) == 256


def test_password_hash_and_the_clone_auth_script(tmp_path):
    encoded = hash_password("s3cret")
    assert verify_password("s3cret", encoded) and not verify_password("wrong", encoded)
    assert encoded != hash_password("s3cret")  # salted
    # The clone's auth script (stdlib only, run by OpenVPN) agrees with the operator side.
    script = tmp_path / "ccrp-auth"
    shutil.copy(ROOT / "templates" / "clone" / "ccrp-auth", script)
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys" / "passwd").write_text(f"nao1:{encoded}\n")
    def auth(user, password, cn="nao1"):
        via = tmp_path / "via"
        via.write_text(f"{user}\n{password}\n")
        env = {"PATH": "/usr/bin:/bin", "common_name": cn}
        return subprocess.run(["python3", str(script), str(via)], env=env).returncode
    assert auth("nao1", "s3cret") == 0
    assert auth("nao1", "wrong") != 0
    assert auth("nao2", "s3cret") != 0
    assert auth("nao1", "s3cret", cn="nao2") != 0

    def tls_verify(depth, cn):  # OpenVPN's tls-verify: depth and subject, the CN in the environment
        env = {"PATH": "/usr/bin:/bin", "X509_0_CN": cn}
        return subprocess.run(["python3", str(script), str(depth), f"CN={cn}"], env=env).returncode
    assert tls_verify(0, "nao1") == 0 and tls_verify(1, "lab-ca") == 0
    assert tls_verify(0, "nao2") != 0 and tls_verify(0, "nao1.power") != 0 and tls_verify(0, "") != 0
    # The robot's power device, once it has its line: its own name and password, nothing else.
    device = hash_password("dev1ce")
    (tmp_path / "keys" / "passwd").write_text(f"nao1:{encoded}\nnao1.power:{device}\n")
    assert tls_verify(0, "nao1.power") == 0 and tls_verify(0, "nao1") == 0
    assert auth("nao1.power", "dev1ce", cn="nao1.power") == 0
    assert auth("nao1.power", "s3cret", cn="nao1.power") != 0  # the robot's password is not the device's
    assert auth("nao1", "dev1ce", cn="nao1") != 0
    assert auth("nao1.power", "dev1ce", cn="nao1") != 0  # the robot's certificate with the device's login
    assert auth("nao1", "s3cret", cn="nao1.power") != 0


def test_a_revoked_robot_stays_out_until_the_operator_reissues(lab):
    """`fleet up` (issue_robot without enroll) must not quietly re-enrol a revoked robot."""
    from ccrp_cli.pki.store import RobotRevoked

    days = lab.inventory.vpn.cert_days
    old = lab.pki.credentials("nao2")
    vpn.revoke(lab, "nao2")
    assert lab.pki.revoked_since("nao2") is not None
    with pytest.raises(RobotRevoked, match="stays unenrolled"):
        lab.pki.issue_robot("nao2", days)
    assert lab.pki.revoked_since("nao2") is not None  # nothing was issued
    # The operator's `vpn issue-cert` lets it back in, with none of the old secrets.
    vpn.issue(lab, "nao2")
    assert lab.pki.revoked_since("nao2") is None
    new = lab.pki.credentials("nao2")
    assert new.password != old.password and new.tls_crypt_key != old.tls_crypt_key
    assert new.client_cert_pem != old.client_cert_pem
    lab.pki.issue_robot("nao2", days)  # and fleet up's ensure is quiet again
    assert lab.pki.credentials("nao2") == new


def test_renew_revokes_the_previous_certificates_and_rotates_both_secrets(lab):
    pki = lab.pki.root
    before = certs(lab)
    old = lab.pki.credentials("nao1")
    renewed = {r["profile"]: r for r in vpn.issue(lab, "nao1", renew=True)}
    assert renewed["client"]["issued"] and renewed["server"]["issued"]
    for cn in ("nao1", "cri-nao1"):
        bad = openssl_verify(pki, before[cn]["path"], crl_check=True)
        assert bad.returncode != 0 and "certificate revoked" in bad.stdout + bad.stderr, cn
        assert openssl_verify(pki, renewed["client" if cn == "nao1" else "server"]["path"], crl_check=True).returncode == 0
    new = lab.pki.credentials("nao1")
    assert new.password != old.password and new.tls_crypt_key != old.tls_crypt_key
    assert verify_password(new.password, new.password_hash) and not verify_password(old.password, new.password_hash)
    assert lab.pki.revoked_since("nao1") is None  # renewed, not revoked


def test_relay_certificates_come_from_their_own_ca_with_a_cn_per_certificate(lab):
    """A robot's VPN certificate must never chain to what relay links trust, and each relay
    certificate has its own CN so the agents can admit exactly the current ones."""
    pki = lab.pki.root
    assert lab.pki.issue_relay("nao1", "10.90.0.10", 30)
    assert not lab.pki.issue_relay("nao1", "10.90.0.10", 30)  # idempotent
    first = lab.pki.relay_cns()["nao1"]
    assert lab.pki.issue_relay("nao1", "10.90.0.20", 30)  # address changed: a new one
    second = lab.pki.relay_cns()["nao1"]
    assert (first, second) == ("relay-nao1-1", "relay-nao1-2")
    relay = certs(lab)[second]["path"]
    relay_ca = ["openssl", "verify", "-CAfile", str(pki / "relay-ca.crt")]
    assert subprocess.run([*relay_ca, relay], capture_output=True).returncode == 0
    robot = subprocess.run([*relay_ca, certs(lab)["nao1"]["path"]], capture_output=True, text=True)
    assert robot.returncode != 0, "a robot's VPN certificate chains to the relay CA"
    assert openssl_verify(pki, relay).returncode != 0, "a relay certificate chains to the VPN CA"
    revoked = vpn.revoke(lab, "nao1", cert="relay")
    assert [r["cn"] for r in revoked] == [second]
    assert "nao1" not in lab.pki.relay_cns()
    assert lab.pki.revoked_since("nao1") is None  # the robot itself stays enrolled


def test_a_password_pair_left_by_a_killed_run_is_replaced(lab):
    """issue_robot writes the hash, then the password: a kill in between must not leave a robot
    whose password its clone's hash refuses."""
    txt = lab.pki.root / "passwords" / "nao1.txt"
    txt.write_text("left-by-a-killed-run\n")
    lab.pki.issue_robot("nao1", 30)
    creds = lab.pki.credentials("nao1")
    assert creds.password != "left-by-a-killed-run" and verify_password(creds.password, creds.password_hash)


def test_issue_fleet_issues_what_fleet_up_needs_in_one_index_save(ccrp_home, monkeypatch):
    """`fleet up`'s batch: every robot's certificates, relay certificate and secrets, the index
    saved once; a second batch changes nothing; a revoked robot is left out."""
    fleet = Fleet.open(LAB)
    vpn.init(fleet)
    vpn.issue(fleet, "nao2")
    vpn.revoke(fleet, "nao2")
    plan = fleet.plan(fleet.store.load_state())
    robots = {r: str(plan[r].common_ip) for r in ("nao1", "nao2", "turtlebot1")}
    saves = []
    monkeypatch.setattr(type(fleet.pki), "_save_index", lambda self, index, real=type(fleet.pki)._save_index: (saves.append(1), real(self, index)))
    assert fleet.pki.issue_fleet(robots, 30) == ["nao1", "turtlebot1"]
    assert len(saves) == 1
    recs = certs(fleet)
    for cn in ("nao1", "cri-nao1", "turtlebot1", "cri-turtlebot1"):
        assert openssl_verify(fleet.pki.root, recs[cn]["path"], crl_check=True).returncode == 0
    assert {c for c in recs if c.startswith("relay-")} == {"relay-nao1-1", "relay-turtlebot1-1"}
    for robot in ("nao1", "turtlebot1"):
        creds = fleet.pki.credentials(robot)
        assert verify_password(creds.password, creds.password_hash) and creds.tls_crypt_key
    assert fleet.pki.issue_fleet(robots, 30) == [] and len(saves) == 1
    assert fleet.pki.revoked_since("nao2") is not None
