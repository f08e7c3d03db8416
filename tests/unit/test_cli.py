"""The command line as users type it: exit codes, one-line errors, --json, files written."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from ccrp_cli import __version__
from tests.conftest import LAB


def test_version_and_help(ccrp):
    assert ccrp("--version").stdout.strip() == f"ccrp {__version__}"
    out = ccrp("--help", check=True).stdout
    for group in ("fleet", "vpn", "render"):
        assert group in out
    assert "issue-cert" in ccrp("vpn", "--help", check=True).stdout


def test_usage_error_is_one_line_exit_2(ccrp):
    proc = ccrp("vpn", "issue-cert", "-i", str(LAB))
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1
    assert "--robot" in proc.stderr and "Traceback" not in proc.stderr
    proc = ccrp("fleet", "explode")
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1


def test_pki_lifecycle_through_the_cli(ccrp, ccrp_home, tmp_path):
    i = ["-i", str(LAB)]
    proc = ccrp("vpn", "list", *i)
    assert proc.returncode == 1 and "vpn init" in proc.stderr  # hint names the fix
    proc = ccrp("vpn", "issue-cert", *i, "--robot", "nao1", "--json", check=True)  # a new fleet: its PKI is made first
    assert "had no PKI yet" in proc.stderr
    issued = json.loads(proc.stdout)
    assert {r["cn"] for r in issued} == {"nao1", "cri-nao1"} and all(r["issued"] for r in issued)
    assert json.loads(ccrp("vpn", "init", *i, "--json", check=True).stdout)["created"] is False
    proc = ccrp("vpn", "issue-cert", *i, "--robot", "nao9")
    assert proc.returncode == 2 and "not in fleet 'lab'" in proc.stderr
    listing = json.loads(ccrp("vpn", "list", *i, "--json", check=True).stdout)
    assert {"serial", "cn", "not_after", "revoked", "path"} <= set(listing[0])
    assert (ccrp_home / "lab" / "pki" / "ca.crt").exists() and (ccrp_home / "lab" / "pki" / "crl.pem").exists()
    ccrp("vpn", "revoke", *i, "--robot", "nao1", check=True)
    listing = {r["cn"]: r for r in json.loads(ccrp("vpn", "list", *i, "--json", check=True).stdout)}
    assert listing["nao1"]["revoked"] and not listing["cri-nao1"]["revoked"]
    proc = ccrp("vpn", "revoke", *i, "--robot", "nao1")
    assert proc.returncode == 1 and "no certificate to revoke" in proc.stderr


def test_render_commands(ccrp, ccrp_home, tmp_path):
    i = ["-i", str(LAB)]
    ud = ccrp("render", "cloud-init", *i, "--robot", "nao2", check=True).stdout
    assert ud.startswith("#cloud-config\n") and "hostname: cri-nao2" in ud
    ccrp("vpn", "init", *i, check=True)
    proc = ccrp("render", "clone-secrets", *i, "--robot", "nao2", "--out", str(tmp_path / "s"))
    assert proc.returncode == 1 and "issue-cert" in proc.stderr
    ccrp("vpn", "issue-cert", *i, "--robot", "nao2", check=True)
    ccrp("render", "clone-secrets", *i, "--robot", "nao2", "--out", str(tmp_path / "s"), check=True)
    assert (tmp_path / "s" / "server.key").exists()
    proc = ccrp("render", "edge", *i, "--robot", "nao2", "--out", str(tmp_path / "e"))
    assert proc.returncode == 2 and "--remote" in proc.stderr and not (tmp_path / "e").exists()
    ccrp("render", "edge", *i, "--robot", "nao2", "--out", str(tmp_path / "e"), "--remote", "198.51.100.7", check=True)
    assert "remote 198.51.100.7 1194" in (tmp_path / "e" / "robot.ovpn").read_text()


def test_cli_import_pulls_no_cloud_sdk():
    code = (
        "import sys, ccrp_cli.cli.main\n"
        "heavy = [m for m in sys.modules if m.split('.')[0] in "
        "{'openstack', 'boto3', 'botocore', 'docker', 'paramiko', 'googleapiclient'} or m.startswith('google.cloud')]\n"
        "print(heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.mark.parametrize("args, wanted", [
    (("snapshot", "build", "-i", "inventories/aws.yaml"), "snapshot bake"),
    (("snapshot", "build", "-i", "inventories/openstack.yaml"), "snapshot bake"),
    (("snapshot", "bake", "-i", "inventories/lab.yaml"), "snapshot build"),
])
def test_a_command_the_backend_cannot_do_is_one_line_exit_2(ccrp, ccrp_home, args, wanted):
    # Checked from the provider's declared abilities, before any SDK or credential is touched.
    proc = ccrp(*args)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and wanted in proc.stderr
    assert len(proc.stderr.strip().splitlines()) <= 2  # the error and its hint
    assert not ccrp_home.exists() or not any(ccrp_home.rglob("state.json"))
