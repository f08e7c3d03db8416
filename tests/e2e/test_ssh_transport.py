"""The SSH transport for real, against OpenSSH in local containers booted like cloud VMs.

Each container runs the real cloud-init (22.4, NoCloud seed) and then sshd: cloud-init creates the
`ccrp` login user (cloudinit.login_user, as every cloud clone's user-data does) with passwordless
sudo and the operator key, generates fresh host keys and prints them on its console (`docker logs`
here; the serial console on a cloud) exactly as it does on a VM: the FINGERPRINTS block through
`logger -s`, the KEYS block on stdout. ccrp pins what it reads there. Nothing is faked between ccrp and sshd.

Containers and the test image carry the labels ccrp-test=ssh-transport and ccrp-test-run=<run>;
a finalizer removes them even when a test fails. Only the containers' own addresses are dialled.
"""

from __future__ import annotations

import base64
import io
import secrets
import stat
import tarfile
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT
from tests.e2e.fleet import NO_DOCKER

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(NO_DOCKER is not None, reason=f"needs a running Docker engine ({NO_DOCKER})"),
]

docker = pytest.importorskip("docker")
paramiko = pytest.importorskip("paramiko")

from ccrp_cli.ops import clones  # noqa: E402
from ccrp_cli.errors import CcrpError  # noqa: E402
from ccrp_cli.fleet import clone_view  # noqa: E402
from ccrp_cli.loader import load_inventory  # noqa: E402
from ccrp_cli.providers import cloud  # noqa: E402
from ccrp_cli.providers.base import CloneRecord, CloneState  # noqa: E402
from ccrp_cli.providers.docker.archive import tar_files  # noqa: E402
from ccrp_cli.render import bundles, cloudinit, openvpn  # noqa: E402
from ccrp_cli.render.files import BundleFile  # noqa: E402
from ccrp_cli.render.view import SECRETS_DIR, VPN_DIR  # noqa: E402
from ccrp_cli.transport.ssh import KnownHosts, SshTransport, fingerprint, fingerprints_from_console  # noqa: E402

RUN = secrets.token_hex(4)
LABELS = {"ccrp-test": "ssh-transport", "ccrp-test-run": RUN}
BASE = "ccrp/base:bookworm"  # the Docker backend's own base image (Debian bookworm + cloud-init)
SEED = "var/lib/cloud/seed/nocloud"
BOOT_TIMEOUT = 90.0

# A cloud VM's first boot, in short. cloud-init prints the host-key fingerprints through
# `logger -s`, which needs a syslog socket: a sink on /dev/log stands in for journald and drains
# what sshd logs there too.
BOOT_SCRIPT = """#!/bin/sh
python3 -c 'import socket; s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM); s.bind("/dev/log"); [s.recv(65536) for _ in iter(int, 1)]' &
while [ ! -S /dev/log ]; do sleep 0.05; done
cloud-init init --local; cloud-init init; cloud-init modules --mode config; cloud-init modules --mode final
mkdir -p /run/sshd
exec /usr/sbin/sshd -D -e
"""

DOCKERFILE = """FROM {base}
RUN if ! command -v sshd >/dev/null || ! command -v sudo >/dev/null; then \\
      apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends openssh-server sudo \\
      && rm -rf /var/lib/apt/lists/*; fi \\
 && rm -f /etc/ssh/ssh_host_* \\
 && mkdir -p /{seed} && printf 'datasource_list: [ NoCloud, None ]\\n' > /etc/cloud/cloud.cfg.d/90-ccrp.cfg
COPY boot /usr/local/sbin/boot
CMD ["/bin/sh", "/usr/local/sbin/boot"]
"""


# -- image, containers, operator key ------------------------------------------------------------


@pytest.fixture(scope="module")
def client():
    c = docker.from_env(timeout=300)
    yield c
    # Whatever a test left behind, even after a failure.
    for ctr in c.containers.list(ignore_removed=True, all=True, filters={"label": f"ccrp-test-run={RUN}"}):
        ctr.remove(force=True, v=True)
    for img in c.images.list(filters={"label": f"ccrp-test-run={RUN}"}):
        c.images.remove(img.id, force=True)
    c.close()


def _base_image(client) -> str:
    """ccrp's base image when present; else a bookworm rootfs from mmdebstrap (Docker Hub is
    not reachable here)."""
    import shutil
    import subprocess

    try:
        client.images.get(BASE)
        return BASE
    except docker.errors.ImageNotFound:
        pass
    if shutil.which("mmdebstrap") is None:
        pytest.skip(f"{BASE} is missing and mmdebstrap is not installed to build a base")
    tag = f"ccrp-test/sshd-base:{RUN}"
    deb = subprocess.Popen(["mmdebstrap", "--variant=minbase", "--include=openssh-server,sudo,python3,cloud-init",
                            "bookworm", "-"], stdout=subprocess.PIPE)
    imp = subprocess.run(["docker", "import", "--change", f"LABEL ccrp-test-run={RUN}", "-", tag], stdin=deb.stdout,
                         capture_output=True)
    deb.stdout.close()
    assert deb.wait() == 0 and imp.returncode == 0, imp.stderr.decode()[-500:]
    return tag


@pytest.fixture(scope="module")
def image(client) -> str:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, text, mode in (("Dockerfile", DOCKERFILE.format(base=_base_image(client), seed=SEED), 0o644),
                                 ("boot", BOOT_SCRIPT, 0o755)):
            info = tarfile.TarInfo(name)
            info.size, info.mode = len(text.encode()), mode
            tar.addfile(info, io.BytesIO(text.encode()))
    buf.seek(0)
    tag = f"ccrp-test/sshd:{RUN}"
    client.images.build(fileobj=buf, custom_context=True, tag=tag, labels=LABELS, rm=True, forcerm=True)
    return tag


class Operator(cloud.CloudProvider):
    """Only for its operator key (the same code path a cloud provider uses)."""


@pytest.fixture(scope="module")
def operator_key(tmp_path_factory) -> tuple[Path, str]:
    op = Operator(load_inventory(ROOT / "inventories" / "openstack.yaml"), tmp_path_factory.mktemp("op"))
    public = op.operator_public_key()  # created 0600 in the store, as for a real fleet
    return op.ssh_key_path, public


def _user_data(public_key: str) -> str:
    data = {
        "locale": "C.UTF-8",
        # The hostname takes (SYS_ADMIN): sudo must resolve it, as a clone's own /etc/hosts does.
        "manage_etc_hosts": True,
        "groups": ["openvpn"],
        "users": [cloudinit.login_user([public_key])],
        # As a cloud clone's user-data does: a tmpfs for the keys at every boot, the VPN directory.
        "bootcmd": cloudinit.every_boot_bootcmd(),
        "runcmd": [["install", "-d", "-m", "0750", "-o", "root", "-g", "openvpn", VPN_DIR]],
    }
    return "#cloud-config\n" + yaml.safe_dump(data, sort_keys=False)


class Vm:
    """One booted container: its address and console."""

    def __init__(self, client, image: str, public_key: str, wait: bool = True) -> None:
        # SYS_ADMIN and no seccomp/AppArmor filter: bootcmd mounts the secrets tmpfs, as on a VM.
        self.container = client.containers.create(image, labels=LABELS, detach=True, cap_add=["SYS_ADMIN"],
                                                  security_opt=["seccomp=unconfined", "apparmor=unconfined"])
        meta = f"instance-id: i-{secrets.token_hex(8)}\nlocal-hostname: cri-nao1\n"
        self.container.put_archive("/", tar_files([(f"{SEED}/meta-data", meta.encode(), 0o600),
                                                   (f"{SEED}/user-data", _user_data(public_key).encode(), 0o600)],
                                                  make_dirs=True))
        self.container.start()
        self.container.reload()
        self.ip = self.container.attrs["NetworkSettings"]["IPAddress"]
        if wait:
            self.wait_sshd()

    def reboot(self) -> None:
        boots = self.console().count("Server listening on 0.0.0.0 port 22")
        self.container.restart(timeout=5)
        self.container.reload()
        self.ip = self.container.attrs["NetworkSettings"]["IPAddress"]
        self.wait_sshd(boots + 1)

    def disk_files(self, path: str) -> dict[str, bytes]:
        """The files under `path` as the container's disk holds them: Docker reads the root
        filesystem from outside, so what a process mounted inside (a tmpfs) is not there, just
        as a cloud snapshot of the boot disk would not hold it."""
        stream, _ = self.container.get_archive(path)
        with tarfile.open(fileobj=io.BytesIO(b"".join(stream))) as tar:
            return {m.name: tar.extractfile(m).read() for m in tar.getmembers() if m.isfile()}

    def console(self) -> str:
        return self.container.logs().decode(errors="replace")

    def wait_sshd(self, boots: int = 1) -> None:
        """Until sshd has started `boots` times (a reboot starts it once more)."""
        deadline = time.monotonic() + BOOT_TIMEOUT
        while self.console().count("Server listening on 0.0.0.0 port 22") < boots:
            assert time.monotonic() < deadline, f"sshd did not start:\n{self.console()[-3000:]}"
            time.sleep(0.2)

    def sh(self, *argv: str) -> str:
        result = self.container.exec_run(list(argv))
        return result.output.decode(errors="replace")

    def accepted_logins(self) -> int:
        return self.console().count("Accepted publickey")

    def host_fingerprints(self) -> set[str]:
        """What `ssh-keygen -lf` says on the host itself (independent of the console)."""
        out = self.sh("sh", "-c", "for f in /etc/ssh/ssh_host_*_key.pub; do ssh-keygen -lf $f; done")
        return {line.split()[1] for line in out.splitlines() if "SHA256:" in line}


@pytest.fixture(scope="module")
def vm(client, image, operator_key) -> Vm:
    return Vm(client, image, operator_key[1])


def _ssh(vm: Vm, key: Path, pins=(), **kw) -> SshTransport:
    return SshTransport(vm.ip, cloud.SSH_USER, key, pins, **kw)


# -- host keys ------------------------------------------------------------------------------------


def test_console_shows_the_real_host_keys(vm):
    assert fingerprints_from_console(vm.console()) == vm.host_fingerprints()


def test_pinned_key_accepted_and_recorded(vm, operator_key, tmp_path):
    known = KnownHosts(tmp_path / "known_hosts")
    pins = fingerprints_from_console(vm.console())
    with _ssh(vm, operator_key[0], pins, known_hosts=known, host_alias="i-pinned") as ssh:
        assert ssh.exec(["id", "-un"]) == (0, "ccrp\n")
    (key_type, b64), = known.keys("i-pinned")
    assert fingerprint(base64.b64decode(b64)) in pins
    assert stat.S_IMODE((tmp_path / "known_hosts").stat().st_mode) == 0o600
    # The next connection needs no pins: known_hosts holds the key under the instance's alias.
    with _ssh(vm, operator_key[0], (), known_hosts=known, host_alias="i-pinned") as ssh:
        assert ssh.exec(["true"])[0] == 0


def test_wrong_pinned_fingerprint_refused_before_any_command(vm, operator_key, tmp_path):
    logins = vm.accepted_logins()
    stranger = paramiko.Ed25519Key.from_private_key(io.StringIO(_new_private_key()))
    wrong = {fingerprint(base64.b64decode(stranger.get_base64()))}
    with pytest.raises(CcrpError, match="not one of the fingerprints pinned from its console") as err:
        _ssh(vm, operator_key[0], wrong, known_hosts=KnownHosts(tmp_path / "kh")).exec(["touch", "/tmp/ran"])
    assert vm.ip in err.value.message
    assert "No such file" in vm.sh("ls", "/tmp/ran")
    assert vm.accepted_logins() == logins  # refused before authentication
    assert not (tmp_path / "kh").exists()


def test_unknown_host_without_pin_refused(vm, operator_key, tmp_path):
    logins = vm.accepted_logins()
    with pytest.raises(CcrpError, match="no pinned host key"):
        _ssh(vm, operator_key[0], (), known_hosts=KnownHosts(tmp_path / "kh")).connect()
    assert vm.accepted_logins() == logins
    assert not (tmp_path / "kh").exists()


def test_trust_on_first_use_warns_and_records(vm, operator_key, tmp_path, capsys):
    known = KnownHosts(tmp_path / "known_hosts")
    with _ssh(vm, operator_key[0], (), known_hosts=known, host_alias="i-tofu", trust_on_first_use=True) as ssh:
        assert ssh.exec(["true"])[0] == 0
    warning = capsys.readouterr().err
    assert "warning: trusting the host key of" in warning and vm.ip in warning and str(known.path) in warning
    assert stat.S_IMODE(known.path.stat().st_mode) == 0o600
    (_, b64), = known.keys("i-tofu")
    assert fingerprint(base64.b64decode(b64)) in vm.host_fingerprints()
    # Once recorded, a different key under the same alias is refused as a change.
    other = paramiko.Ed25519Key.from_private_key(io.StringIO(_new_private_key()))
    known.path.write_text(f"i-tofu ssh-ed25519 {other.get_base64()}\n")
    with pytest.raises(CcrpError, match="host key of .* changed"):
        _ssh(vm, operator_key[0], (), known_hosts=known, host_alias="i-tofu").connect()


def test_a_clone_is_reached_through_the_gateway_with_both_keys_pinned(vm, fresh_vm, operator_key, tmp_path):
    """ProxyJump (an entry gateway's fleet): the gateway `vm` carries the SSH connection to the clone
    `fresh_vm`, which sees it come from the gateway; each host's key is pinned on its own, and a
    clone whose key is not the pinned one is refused though the gateway is trusted. Nothing listening
    behind the gateway is retried as a booting guest, and the error names the jump."""
    known = KnownHosts(tmp_path / "known_hosts")
    gateway = _ssh(vm, operator_key[0], fingerprints_from_console(vm.console()), known_hosts=known, host_alias="i-gw")
    try:
        fresh_vm.wait_sshd()
        with _ssh(fresh_vm, operator_key[0], fingerprints_from_console(fresh_vm.console()), known_hosts=known,
                  host_alias="i-clone", via=gateway) as clone:
            rc, seen = clone.exec(["sh", "-c", 'echo "$SSH_CONNECTION"'])
            assert rc == 0 and seen.split()[0] == vm.ip, seen  # the clone's sshd saw the gateway's address
            assert "via" in clone.where and vm.ip in clone.where
        assert {alias for alias, *_ in known._entries()} == {"i-gw", "i-clone"}
        # A clone offering another key than the one pinned is refused before authentication.
        logins = fresh_vm.accepted_logins()
        stranger = paramiko.Ed25519Key.from_private_key(io.StringIO(_new_private_key()))
        wrong = {fingerprint(base64.b64decode(stranger.get_base64()))}
        with pytest.raises(CcrpError, match="not one of the fingerprints pinned"):
            _ssh(fresh_vm, operator_key[0], wrong, known_hosts=KnownHosts(tmp_path / "kh2"), via=gateway).connect()
        assert fresh_vm.accepted_logins() == logins
        # Nothing listening behind the gateway: the jump's "connect failed" is a booting guest's error.
        from ccrp_cli.retry import Backoff
        with pytest.raises(CcrpError, match="via"):
            SshTransport(fresh_vm.ip, cloud.SSH_USER, operator_key[0], port=2222, via=gateway,
                         backoff=Backoff(attempts=2, base=0.1, cap=0.1)).connect()
    finally:
        gateway.close()


def _new_private_key() -> str:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519

    return ed25519.Ed25519PrivateKey.generate().private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()).decode()


# -- commands and files ---------------------------------------------------------------------------


@pytest.fixture
def ssh(vm, operator_key):
    with _ssh(vm, operator_key[0], fingerprints_from_console(vm.console())) as t:
        yield t


def test_exec_returns_exit_code_and_output(ssh):
    rc, out = ssh.exec(["sh", "-c", "echo out; echo err >&2; exit 3"])
    assert rc == 3 and "out\n" in out and "err\n" in out
    with pytest.raises(TypeError):
        ssh.exec("echo hi")  # a shell string is never accepted


def test_exec_passes_names_with_spaces_and_quotes_verbatim(ssh):
    tricky = ["a b", "it's", 'say "hi"', "$(touch /tmp/injected)", "; rm -rf /tmp/x #", "back\\slash"]
    rc, out = ssh.exec(["printf", "%s\\n", *tricky])
    assert rc == 0 and out.splitlines() == tricky
    assert ssh.exec(["test", "-e", "/tmp/injected"])[0] == 1
    name = "/tmp/clone 'nao1' \"x\""
    assert ssh.exec(["touch", name])[0] == 0
    assert ssh.exec(["ls", name]) == (0, name + "\n")


def test_exec_timeout(ssh):
    t0 = time.monotonic()
    with pytest.raises(CcrpError, match="did not finish within 1 s"):
        ssh.exec(["sleep", "30"], timeout=1)
    assert time.monotonic() - t0 < 5


def test_put_files_installs_mode_group_and_leaves_no_temp(ssh, vm):
    files = [
        BundleFile("server.key", "-----BEGIN TEST KEY-----\nnot a real key\n", 0o600, f"{VPN_DIR}/server.key"),
        BundleFile("passwd", "nao1:$scrypt$...\n", 0o640, f"{VPN_DIR}/passwd", "openvpn"),
        BundleFile("ca.crt", "ca\n", 0o644, f"{VPN_DIR}/ca.crt"),
        BundleFile("odd", "name with space\n", 0o644, f"{VPN_DIR}/it's odd"),
    ]
    ssh.put_files(files)
    for f in files:
        st = vm.sh("stat", "-c", "%a %U %G", f.dest).split()
        assert st == [f"{f.mode:o}", "root", f.group], (f.dest, st)
        assert vm.sh("cat", f.dest) == f.content
    assert vm.sh("sh", "-c", "ls -A /tmp | grep ccrp-push || true") == ""
    # A destination that cannot be written fails loudly and still cleans up.
    with pytest.raises(CcrpError, match="install"):
        ssh.put_files([BundleFile("x", "x", 0o600, "/nonexistent/dir/x")])
    assert vm.sh("sh", "-c", "ls -A /tmp | grep ccrp-push || true") == ""


# -- CloudProvider over SSH, end to end -------------------------------------------------------------


class ContainerCloud(cloud.CloudProvider):
    """A cloud whose instances are these containers: query() gives their address, the console
    is `docker logs`. Everything SSH (wait_ready, and its transport's exec and push_files) is CloudProvider's own."""

    kind = "containers"

    def __init__(self, inv, workdir, vms: dict[str, Vm], console_of: dict[str, Vm] | None = None):
        super().__init__(inv, workdir)
        self.vms, self.console_of = vms, console_of or vms

    def query(self) -> dict[str, CloneRecord]:
        return {r: CloneRecord(robot=r, provider_id=v.container.id[:12], state=CloneState.RUNNING, status="running", public_ip=v.ip)
                for r, v in self.vms.items()}

    def console_output(self, robot: str) -> str:
        return self.console_of[robot].console()


@pytest.fixture
def fresh_vm(client, image, operator_key):
    vm = Vm(client, image, operator_key[1], wait=False)
    yield vm
    vm.container.remove(force=True, v=True)


def test_cloud_provider_wait_ready_push_exec(lab, fresh_vm, operator_key, monkeypatch):
    monkeypatch.setattr(cloud, "CONSOLE_POLL", 0.5)
    inv = load_inventory(ROOT / "inventories" / "openstack.yaml")
    workdir = operator_key[0].parent.parent  # the store holding the operator key
    provider = ContainerCloud(inv, workdir, {"nao1": fresh_vm})
    try:
        # Called while the instance is still booting: waits for the console's host keys.
        t0 = time.monotonic()
        provider.wait_ready("nao1", timeout=BOOT_TIMEOUT)
        took = time.monotonic() - t0
        assert "status: done" in fresh_vm.sh("cloud-init", "status")
        alias = fresh_vm.container.id[:12]
        recorded = KnownHosts(provider.known_hosts_path).keys(alias)
        assert len(recorded) == 1
        assert stat.S_IMODE(provider.known_hosts_path.stat().st_mode) == 0o600

        # exec runs as root (like a command in a Docker clone); exit codes come back.
        assert provider.transport.exec("nao1", ["id", "-u"]) == (0, "0\n")
        assert provider.transport.exec("nao1", ["sh", "-c", "exit 7"])[0] == 7

        # The real secrets bundle of robot nao1, pushed and then found current by ensure_clone's check.
        view = clone_view(lab, lab.load_allocated(), "nao1")
        files = bundles.clone_secrets(view, lab.pki.credentials("nao1"))
        assert not clones.files_current(provider, "nao1", files)
        provider.transport.push_files("nao1", files)
        assert clones.files_current(provider, "nao1", files)
        for f in files:
            assert fresh_vm.sh("stat", "-c", "%a %G", f.dest).split() == [f"{f.mode:o}", f.group]
        assert fresh_vm.sh("sh", "-c", "ls -A /tmp /dev/shm | grep ccrp-push || true") == ""
        # A unit that cannot restart (no systemd in this container) is an error, not a shrug.
        with pytest.raises(CcrpError, match="systemctl restart ccrp-openvpn.service"):
            provider.transport.push_files("nao1", files[:1], restart=["ccrp-openvpn.service"])

        # Another run (a new provider, nothing in memory) connects from known_hosts alone, even
        # once the console has scrolled the keys away.
        blank = type("Blank", (), {"console": lambda self: ""})()
        later = ContainerCloud(inv, workdir, {"nao1": fresh_vm}, console_of={"nao1": blank})
        try:
            assert later.transport.exec("nao1", ["hostname"])[0] == 0
            later.wait_ready("nao1", timeout=30)
        finally:
            later.close()
    finally:
        provider.close()
    print(f"wait_ready from container start: {took:.1f} s")


def test_secrets_are_in_memory_never_on_the_disk_and_come_back_after_a_reboot(lab, fresh_vm, operator_key, monkeypatch):
    monkeypatch.setattr(cloud, "CONSOLE_POLL", 0.5)
    inv = load_inventory(ROOT / "inventories" / "openstack.yaml")
    workdir = operator_key[0].parent.parent
    view = clone_view(lab, lab.load_allocated(), "nao1")
    files = bundles.clone_secrets(view, lab.pki.credentials("nao1"))
    key = next(f for f in files if f.name == "server.key").content.encode()

    def push(provider) -> None:
        clones.prepare_secrets_dir(provider, "nao1")
        provider.transport.push_files("nao1", files)
        assert clones.files_current(provider, "nao1", files)

    provider = ContainerCloud(inv, workdir, {"nao1": fresh_vm})
    try:
        provider.wait_ready("nao1", timeout=BOOT_TIMEOUT)
        # Beside the keys, as a clone's user-data writes it: the server config, on the disk.
        provider.transport.push_files("nao1", [BundleFile("server.conf", openvpn.server_conf(view), 0o644, f"{VPN_DIR}/server.conf")])
        push(provider)
        assert fresh_vm.sh("stat", "-f", "-c", "%T", SECRETS_DIR).strip() == "tmpfs"
        assert fresh_vm.sh("stat", "-c", "%a %U %G", SECRETS_DIR).split() == ["751", "root", "openvpn"]
        assert fresh_vm.sh("cat", f"{SECRETS_DIR}/server.key").encode() == key
        assert clones.health(provider, "nao1")["secrets"] is True
        # What a snapshot of the disk would capture: the VPN directory without a single key.
        on_disk = fresh_vm.disk_files(VPN_DIR)
        assert "ccrp/server.conf" in on_disk, sorted(on_disk)
        assert not any(name.startswith("ccrp/keys/") for name in on_disk), sorted(on_disk)
        assert not any(key in content for content in on_disk.values())
    finally:
        provider.close()

    fresh_vm.reboot()
    provider = ContainerCloud(inv, workdir, {"nao1": fresh_vm})
    try:
        # bootcmd mounted a fresh, empty tmpfs; the next `fleet up` sees that and pushes again.
        assert fresh_vm.sh("stat", "-f", "-c", "%T", SECRETS_DIR).strip() == "tmpfs"
        assert fresh_vm.sh("ls", "-A", SECRETS_DIR) == ""
        assert clones.health(provider, "nao1")["secrets"] is False
        assert not clones.files_current(provider, "nao1", files)
        push(provider)
        # No tmpfs there (an image or user-data from elsewhere): refused before any key is sent.
        fresh_vm.sh("umount", SECRETS_DIR)
        with pytest.raises(CcrpError, match="on its root disk"):
            clones.prepare_secrets_dir(provider, "nao1")
        assert fresh_vm.sh("ls", "-A", SECRETS_DIR) == ""
    finally:
        provider.close()


def test_cloud_provider_refuses_a_console_of_another_instance(vm, fresh_vm, operator_key, monkeypatch):
    """The address answers with keys other than those the instance's console printed (a recycled
    IP, a man in the middle): wait_ready refuses and records nothing."""
    monkeypatch.setattr(cloud, "CONSOLE_POLL", 0.5)
    fresh_vm.wait_sshd()
    inv = load_inventory(ROOT / "inventories" / "openstack.yaml")
    provider = ContainerCloud(inv, operator_key[0].parent.parent, {"nao1": fresh_vm}, console_of={"nao1": vm})
    logins = fresh_vm.accepted_logins()
    try:
        with pytest.raises(CcrpError, match="not one of the fingerprints pinned"):
            provider.wait_ready("nao1", timeout=30)
    finally:
        provider.close()
    assert fresh_vm.accepted_logins() == logins
    assert KnownHosts(provider.known_hosts_path).keys(fresh_vm.container.id[:12]) == []


def test_cloud_provider_without_console_keys_refuses_unless_tofu(fresh_vm, operator_key, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cloud, "CONSOLE_POLL", 0.2)
    monkeypatch.setattr(cloud, "TOFU_CONSOLE_WAIT", 1.0)
    fresh_vm.wait_sshd()
    inv = load_inventory(ROOT / "inventories" / "openstack.yaml")
    blank = type("Blank", (), {"console": lambda self: "no keys printed here\n"})()
    store = tmp_path / "store"
    store.mkdir()
    # Same operator key, a store of its own (so known_hosts starts empty).
    (store / "ssh").mkdir()
    (store / "ssh" / "id_ed25519").write_bytes(operator_key[0].read_bytes())
    (store / "ssh" / "id_ed25519").chmod(0o600)
    provider = ContainerCloud(inv, store, {"nao1": fresh_vm}, console_of={"nao1": blank})
    try:
        with pytest.raises(CcrpError, match="printed no SSH host keys"):
            provider.wait_ready("nao1", timeout=2)
        monkeypatch.setenv(cloud.TOFU_ENV, "1")
        tofu = ContainerCloud(inv, store, {"nao1": fresh_vm}, console_of={"nao1": blank})
        try:
            tofu.wait_ready("nao1", timeout=60)
        finally:
            tofu.close()
    finally:
        provider.close()
    assert "trusting the host key" in capsys.readouterr().err
    assert len(KnownHosts(store / "known_hosts").keys(fresh_vm.container.id[:12])) == 1
