"""A libvirt fleet through a remote URI (`qemu+ssh://`), end to end: `ccrp snapshot build` uploading
the golden volume, `ccrp fleet up` of one VM clone (its NoCloud seed uploaded, its console read
back for the host keys ccrp pins), `ccrp status` and `ccrp clone exec` on it, `ccrp robot sim`
refused in one line (a simulated robot needs the libvirt host to be this one), and `ccrp fleet down`
leaving nothing, every libvirt call carried by libvirt's ssh transport.

The "remote" host is this machine reached over SSH on loopback, through an sshd of the test's own
(127.0.0.1, a free port, root by key only, its host key pinned in a known_hosts file the ssh
client is held to): what a lab's libvirt server behind SSH is, but for the route to its NAT network,
which ccrp's SSH to the clone takes here as it would through a route or a jump host there.

Opt-in (CCRP_E2E_LIBVIRT_REMOTE=1): it needs openssh-server's sshd beside libvirtd, and its VM boots
in minutes under TCG. Distro: ROS 1 Noetic (the run's clone image, shared with the scenarios)."""

from __future__ import annotations

import json
import os
import re
import secrets
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from ccrp_cli.providers.libvirt.settings import URI_PARAMS_ENV
from tests.libvirt_host import gate

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.slow, pytest.mark.root]

SKIP = gate() or (None if os.environ.get("CCRP_E2E_LIBVIRT_REMOTE") == "1" else
                  "set CCRP_E2E_LIBVIRT_REMOTE=1 for a fleet through qemu+ssh:// (needs openssh-server's sshd)")
if not SKIP and not Path("/usr/sbin/sshd").exists():
    SKIP = "no sshd (apt-get install openssh-server)"
if SKIP:
    pytest.skip(SKIP, allow_module_level=True)


def ccrp(home: Path, *args: str, timeout: float = 1800) -> subprocess.CompletedProcess:
    env = {**os.environ, "CCRP_HOME": str(home)}
    env.pop("CCRP_INVENTORY", None)
    return subprocess.run([sys.executable, "-m", "ccrp_cli", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def sshd(tmp_path_factory):
    """An sshd of the test's own on 127.0.0.1 and what a client needs to reach it with its host key
    verified: (port, client key, ssh wrapper that pins the host key, sshd's log)."""
    d = tmp_path_factory.mktemp("sshd")
    d.chmod(0o700)
    for name in ("host", "client"):
        subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f", str(d / name)], check=True)
    (d / "authorized_keys").write_text((d / "client.pub").read_text())
    port = free_port()
    key_type, key = (d / "host.pub").read_text().split()[:2]
    (d / "known_hosts").write_text(f"[127.0.0.1]:{port} {key_type} {key}\n")
    wrapper = d / "ssh"
    wrapper.write_text(f'#!/bin/sh\nexec ssh -o UserKnownHostsFile={d}/known_hosts -o StrictHostKeyChecking=yes '
                       f'-o BatchMode=yes -o IdentitiesOnly=yes "$@"\n')
    wrapper.chmod(0o700)
    (d / "sshd_config").write_text(
        f"Port {port}\nListenAddress 127.0.0.1\nHostKey {d}/host\nAuthorizedKeysFile {d}/authorized_keys\n"
        "PermitRootLogin prohibit-password\nPasswordAuthentication no\nKbdInteractiveAuthentication no\n"
        f"UsePAM no\nStrictModes no\nPidFile {d}/sshd.pid\nLogLevel INFO\n")
    Path("/run/sshd").mkdir(mode=0o755, exist_ok=True)  # its privilege separation directory
    log = open(d / "sshd.log", "w")
    proc = subprocess.Popen(["/usr/sbin/sshd", "-D", "-e", "-f", str(d / "sshd_config")], stdout=log, stderr=log)
    try:
        for _ in range(50):
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                time.sleep(0.2)
        yield port, d / "client", wrapper, d / "sshd.log"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        log.close()


@pytest.fixture(scope="module")
def remote_fleet(tmp_path_factory, clone_images, sshd):
    from ccrp_cli.ops.init import free, used_networks

    from tests.e2e.test_libvirt import free_public

    port, key, wrapper, _log = sshd
    clone_images("noetic")  # snapshot build finds the recipe's layers in Docker's cache
    tmp = tmp_path_factory.mktemp("libvirt-remote")
    home = tmp / "home"
    used = used_networks()
    # The client key is the inventory's (a URI may name it); the wrapper that pins the host key is this
    # machine's, from the environment: an inventory's URI cannot name a program (settings.py).
    uri = f"qemu+ssh://root@127.0.0.1:{port}/system?keyfile={key}"
    inv = {"fleet": f"lr{secrets.token_hex(3)}",
           "provider": {"kind": "libvirt", "uri": uri, "accel": os.environ.get("CCRP_LIBVIRT_ACCEL", "auto"),
                        "memory_mb": 1536, "vcpus": 1, "public_cidr": free_public(used)},
           "ros": {"distro": "noetic"}, "vpn": {"pool": free("vpn", used)}, "common": {"cidr": free("common", used)},
           "robots": [{"name": "nao1"}]}
    path = tmp / "ccrp.yaml"
    path.write_text(yaml.safe_dump(inv, sort_keys=False))
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv(URI_PARAMS_ENV, f"command={wrapper}")
            yield {"home": home, "path": str(path), "fleet": inv["fleet"], "uri": uri, "wrapper": wrapper}
    finally:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv(URI_PARAMS_ENV, f"command={wrapper}")
            ccrp(home, "fleet", "down", "-i", str(path), timeout=600)
        import libvirt

        conn = libvirt.open("qemu:///system")  # the same host, asked directly: what is left of the fleet
        try:
            pool = conn.storagePoolLookupByName("ccrp")
            pool.refresh(0)
            for vol in pool.listAllVolumes(0):
                if vol.name().startswith(f"ccrp-{inv['fleet']}-"):
                    vol.delete(0)
        finally:
            conn.close()


def test_a_fleet_through_qemu_ssh_builds_boots_serves_and_goes(remote_fleet, sshd):
    home, path, fleet = remote_fleet["home"], remote_fleet["path"], remote_fleet["fleet"]
    # The same wrapper named by the inventory is refused in one line (exit 2): it would run a program.
    named = Path(path).with_name("named.yaml")
    named.write_text(Path(path).read_text().replace(remote_fleet["uri"], f"{remote_fleet['uri']}&command={remote_fleet['wrapper']}"))
    refused = ccrp(home, "fleet", "validate", "-i", str(named), timeout=60)
    assert refused.returncode == 2 and "parameter command is refused" in refused.stderr, refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1, refused.stderr
    timings = {}
    t0 = time.monotonic()
    built = ccrp(home, "snapshot", "build", "-i", path, "--json")
    timings["snapshot build (golden volume uploaded over ssh)"] = time.monotonic() - t0
    assert built.returncode == 0, built.stderr[-3000:]

    t0 = time.monotonic()
    up = ccrp(home, "fleet", "up", "-i", path)
    timings["fleet up (1 VM clone)"] = time.monotonic() - t0
    assert up.returncode == 0, up.stderr[-3000:]

    status = ccrp(home, "status", "-i", path, "--json", timeout=300)
    assert status.returncode == 0, status.stderr[-2000:]
    [row] = json.loads(status.stdout)
    assert row["phase"] == "ready" and row["state"] == "running" and row["master_reachable"] is True, row

    out = ccrp(home, "clone", "exec", "-i", path, "--robot", "nao1", "--", "echo", "served", timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "served", out.stdout + out.stderr

    sim = ccrp(home, "robot", "sim", "-i", path, "--robot", "nao1", timeout=300)
    assert sim.returncode == 1 and "is not this machine" in sim.stderr and "Traceback" not in sim.stderr, sim.stderr

    t0 = time.monotonic()
    down = ccrp(home, "fleet", "down", "-i", path, timeout=600)
    timings["fleet down"] = time.monotonic() - t0
    assert down.returncode == 0, down.stderr[-2000:]
    import libvirt

    conn = libvirt.open("qemu:///system")
    try:
        assert not [d.name() for d in conn.listAllDomains(0) if d.name().startswith(f"ccrp-{fleet}-")]
        assert not [n.name() for n in conn.listAllNetworks(0) if n.name().startswith(f"ccrp-{fleet}-")]
    finally:
        conn.close()
    # Every one of those commands reached libvirtd through the test's sshd, as root, by key.
    logins = re.findall(r"Accepted publickey for root from 127\.0\.0\.1", sshd[3].read_text())
    timings["ssh logins to the libvirt host"] = len(logins)
    assert len(logins) >= 5, sshd[3].read_text()[-2000:]
    print(f"\nlibvirt remote e2e timings (s): {json.dumps({k: round(v, 1) for k, v in timings.items()})}")
