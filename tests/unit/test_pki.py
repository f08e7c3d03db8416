"""The fleet PKI, checked with the openssl command line as the oracle."""

from __future__ import annotations

import datetime as dt
import os
import shutil
import subprocess

import pytest
from cryptography import x509

from ccrp_cli import vpn
from ccrp_cli.fleet import Fleet
from ccrp_cli.pki.secrets import hash_password, tls_crypt_key, verify_password
from tests.conftest import LAB, ROOT

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")


def openssl_verify(pki, cert, crl_check=False):
    args = ["openssl", "verify", "-CAfile", str(pki / "ca.crt")]
    if crl_check:
        args += ["-crl_check", "-CRLfile", str(pki / "crl.pem")]
    return subprocess.run([*args, str(cert)], capture_output=True, text=True)


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
