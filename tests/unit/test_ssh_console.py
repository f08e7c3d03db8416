"""Host-key pinning from the serial console: the parser on consoles as the clouds print them, and
the paramiko host-key policy built on it (real keys, generated here; no network)."""

from __future__ import annotations

import errno
import itertools
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.retry import ErrorClass
from ccrp_cli.transport.ssh import (
    KnownHosts,
    PinnedHostKeyPolicy,
    classify_connect,
    fingerprint,
    fingerprints_from_console,
    wait_listening,
)

paramiko = pytest.importorskip("paramiko")
_SEQ = itertools.count()


def _keys(tmp_path: Path, n: int = 2) -> list[tuple[str, str, str]]:
    """n fresh host keys: (type, base64, fingerprint computed by ssh-keygen when present)."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec, ed25519

    out = []
    for key in [ed25519.Ed25519PrivateKey.generate(), ec.generate_private_key(ec.SECP256R1())][:n]:
        line = key.public_key().public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH).decode()
        key_type, b64 = line.split()
        pub = tmp_path / f"key{next(_SEQ)}.pub"
        pub.write_text(f"{line} root@cri-nao1\n")
        if shutil.which("ssh-keygen"):
            fp = subprocess.run(["ssh-keygen", "-lf", str(pub)], capture_output=True, text=True, check=True).stdout.split()[1]
        else:  # pragma: no cover - the machine has openssh-client
            fp = fingerprint(__import__("base64").b64decode(b64))
        out.append((key_type, b64, fp))
    return out


def _console(keys, prefix: str = "", fps: bool = True, full: bool = True, eol: str = "\n") -> str:
    """What cloud-init's cc_keys_to_console prints (as on AWS, where each line starts with "ec2: ")."""
    names = {"ssh-ed25519": "ED25519", "ecdsa-sha2-nistp256": "ECDSA"}
    lines = [f"{prefix}#############################################################"]
    if fps:
        lines.append(f"{prefix}-----BEGIN SSH HOST KEY FINGERPRINTS-----")
        lines += [f"{prefix}256 {fp} root@cri-nao1 ({names[t]})" for t, _, fp in keys]
        lines.append(f"{prefix}-----END SSH HOST KEY FINGERPRINTS-----")
    lines.append(f"{prefix}#############################################################")
    if full:
        lines.append("-----BEGIN SSH HOST KEY KEYS-----")
        lines += [f"{t} {b64} root@cri-nao1" for t, b64, _ in keys]
        lines.append("-----END SSH HOST KEY KEYS-----")
    return eol.join(lines) + eol


BOOT_NOISE = (
    "[    0.000000] Linux version 5.4.0-1045-aws (buildd@lcy01-amd64-025)\n"
    "[   11.204551] cloud-init[613]: Cloud-init v. 22.4.2 running 'init' at Fri, 21 Nov 2025 06:00:01 +0000.\n"
    "ci-info: +++++++++++++++++++++++Net device info+++++++++++++++++++++++\n"
)


def test_fingerprints_match_ssh_keygen(tmp_path):
    keys = _keys(tmp_path)
    text = BOOT_NOISE + _console(keys, prefix="ec2: ") + "Cloud-init v. 22.4.2 finished at ...\n"
    assert fingerprints_from_console(text) == {fp for _, _, fp in keys}


def test_fingerprint_of_a_full_key_equals_ssh_keygen(tmp_path):
    import base64

    for _, b64, fp in _keys(tmp_path):
        assert fingerprint(base64.b64decode(b64)) == fp


def test_prefixed_lines_and_crlf(tmp_path):
    keys = _keys(tmp_path)
    text = _console(keys, prefix="[   25.123456] cloud-init[1234]: ", eol="\r\n")
    assert fingerprints_from_console(text) == {fp for _, _, fp in keys}


def test_keys_block_alone_is_enough(tmp_path):
    keys = _keys(tmp_path)
    assert fingerprints_from_console(_console(keys, fps=False)) == {fp for _, _, fp in keys}


def test_fingerprints_block_alone_is_enough(tmp_path):
    keys = _keys(tmp_path)
    assert fingerprints_from_console(_console(keys, full=False)) == {fp for _, _, fp in keys}


def test_nothing_before_the_blocks_are_complete(tmp_path):
    keys = _keys(tmp_path)
    whole = _console(keys)
    assert fingerprints_from_console("") == frozenset()
    assert fingerprints_from_console(BOOT_NOISE) == frozenset()
    # Cut the console in the middle of the fingerprints block: nothing is trusted yet.
    cut = whole[: whole.index("-----END SSH HOST KEY FINGERPRINTS-----")]
    assert fingerprints_from_console(cut) == frozenset()


def test_fingerprint_lines_outside_a_block_are_ignored(tmp_path):
    (_, _, fp), = _keys(tmp_path, 1)
    assert fingerprints_from_console(f"256 {fp} root@evil (ED25519)\n") == frozenset()


def test_the_last_boot_wins(tmp_path):
    old, new = _keys(tmp_path, 1), _keys(tmp_path, 1)
    text = _console(old) + BOOT_NOISE + _console(new)
    assert fingerprints_from_console(text) == {new[0][2]}


def test_md5_and_garbled_lines_are_not_trusted(tmp_path):
    keys = _keys(tmp_path, 1)
    text = (
        "-----BEGIN SSH HOST KEY FINGERPRINTS-----\n"
        "ec2: 2048 9a:5f:12:34:56:78:9a:bc:de:f0:12:34:56:78:9a:bc root@old (RSA)\n"
        "ec2: 256 SHA256:short root@x (ED25519)\n"
        "-----END SSH HOST KEY FINGERPRINTS-----\n"
        "-----BEGIN SSH HOST KEY KEYS-----\n"
        "ssh-ed25519 AAAA$$$notbase64 root@x\n"
        f"{keys[0][0]} {keys[0][1]} root@cri-nao1\n"
        "-----END SSH HOST KEY KEYS-----\n"
    )
    assert fingerprints_from_console(text) == {keys[0][2]}


# -- the host-key policy ---------------------------------------------------------------------------


class _Client:
    def __init__(self):
        self.keys = paramiko.HostKeys()

    def get_host_keys(self):
        return self.keys


def _server_key():
    return paramiko.Ed25519Key.from_private_key(__import__("io").StringIO(_openssh_private()))


def _openssh_private() -> str:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519

    return ed25519.Ed25519PrivateKey.generate().private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()).decode()


def test_policy_accepts_a_pinned_key_and_records_it(tmp_path):
    key = _server_key()
    known = KnownHosts(tmp_path / "known_hosts")
    client = _Client()
    PinnedHostKeyPolicy("192.0.2.7", {fingerprint(key.asbytes())}, known, "i-0abc").missing_host_key(client, "192.0.2.7", key)
    assert client.keys.lookup("192.0.2.7")["ssh-ed25519"] == key
    assert known.keys("i-0abc") == [("ssh-ed25519", key.get_base64())]
    assert (tmp_path / "known_hosts").stat().st_mode & 0o777 == 0o600


def test_policy_refuses_a_key_not_pinned(tmp_path):
    key, other = _server_key(), _server_key()
    known = KnownHosts(tmp_path / "known_hosts")
    with pytest.raises(CcrpError, match=r"not one of the fingerprints pinned") as err:
        PinnedHostKeyPolicy("192.0.2.7", {fingerprint(other.asbytes())}, known).missing_host_key(_Client(), "192.0.2.7", key)
    assert fingerprint(key.asbytes()) in err.value.message
    assert not (tmp_path / "known_hosts").exists()


def test_policy_refuses_without_pins_unless_tofu(tmp_path, capsys):
    key = _server_key()
    known = KnownHosts(tmp_path / "known_hosts")
    with pytest.raises(CcrpError, match="no pinned host key"):
        PinnedHostKeyPolicy("192.0.2.7", (), known).missing_host_key(_Client(), "192.0.2.7", key)
    assert not (tmp_path / "known_hosts").exists()
    warnings = []
    PinnedHostKeyPolicy("192.0.2.7", (), known, "i-0abc", trust_on_first_use=True,
                        warn=warnings.append).missing_host_key(_Client(), "192.0.2.7", key)
    assert len(warnings) == 1 and fingerprint(key.asbytes()) in warnings[0] and "first use" in warnings[0]
    assert known.keys("i-0abc") == [("ssh-ed25519", key.get_base64())]


def test_connect_errors_worth_a_retry():
    from paramiko.ssh_exception import NoValidConnectionsError

    assert classify_connect(ConnectionRefusedError()) is ErrorClass.RETRYABLE
    assert classify_connect(TimeoutError()) is ErrorClass.RETRYABLE
    assert classify_connect(NoValidConnectionsError({("192.0.2.7", 22): ConnectionRefusedError()})) is ErrorClass.RETRYABLE
    assert classify_connect(NoValidConnectionsError({("192.0.2.7", 22): PermissionError()})) is ErrorClass.FATAL
    assert classify_connect(paramiko.AuthenticationException()) is ErrorClass.FATAL
    assert classify_connect(paramiko.SSHException("No existing session")) is ErrorClass.RETRYABLE  # closed mid-handshake
    assert classify_connect(paramiko.SSHException("Incompatible ssh peer (no acceptable kex algorithm)")) is ErrorClass.FATAL
    assert classify_connect(paramiko.BadHostKeyException("h", _server_key(), _server_key())) is ErrorClass.FATAL
    assert classify_connect(CcrpError("pin mismatch")) is ErrorClass.FATAL
    # A started server behind a cloud router before its guest answers ARP (a real Nova).
    unreachable = OSError(errno.EHOSTUNREACH, "No route to host")
    assert classify_connect(NoValidConnectionsError({("192.0.2.7", 22): unreachable})) is ErrorClass.RETRYABLE
    assert classify_connect(OSError(errno.ENETUNREACH, "Network is unreachable")) is ErrorClass.FATAL


def test_wait_listening_waits_for_a_late_sshd_and_gives_up_in_one_line():
    """A started clone's sshd listens only once it has booted: wait_listening waits for it on a real
    socket (a port that refuses first, then listens), and names the address when it never does."""
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # refused until the listener below binds it
    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    late = threading.Timer(0.5, lambda: (listener.bind(("127.0.0.1", port)), listener.listen()))
    late.start()
    try:
        t0 = time.monotonic()
        wait_listening("127.0.0.1", port, timeout=10, interval=0.1)
        assert 0.4 < time.monotonic() - t0 < 5
    finally:
        late.join()
        listener.close()
    with pytest.raises(CcrpError, match=rf"^SSH to 127.0.0.1:{port} did not answer within 1 s$"):
        wait_listening("127.0.0.1", port, timeout=1, interval=0.1)


def test_wait_listening_through_a_jump_host_waits_for_a_guest_still_booting(monkeypatch):
    """Behind the entry gateway a clone is reached through a direct-tcpip channel of the gateway's.
    While the clone boots the gateway answers "connect failed" (refused, no route) or is still
    trying when the channel's timeout runs out (no SYN answered: paramiko's "Timeout opening
    channel"); both mean "booting", as for a direct connection (a real OpenStack's `clone start`
    behind the gateway failed at once on the second). So does paramiko's "Unable to open channel."
    while the gateway's connection is up: a "connect failed" that a concurrent open took (a real
    OpenStack's `fleet up` failed a clone on it). The jump host's own refusals stay errors."""
    from ccrp_cli.transport.ssh import SshTransport

    answers = iter([paramiko.SSHException("Timeout opening channel."),
                    paramiko.ChannelException(paramiko.common.OPEN_FAILED_CONNECT_FAILED, "No route to host"),
                    # Another thread's channel took this one's reason (paramiko keeps one per connection).
                    paramiko.SSHException("Unable to open channel."),
                    "channel"])

    class Transport:
        def is_active(self):
            return True

        def open_channel(self, kind, dest, src, timeout):
            assert kind == "direct-tcpip" and dest == ("10.90.0.11", 22)
            answer = next(answers)
            if isinstance(answer, Exception):
                raise answer
            return Channel()

    class Channel:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    class Client:
        def get_transport(self):
            return Transport()

    gateway = SshTransport.__new__(SshTransport)
    gateway.host, gateway._client = "198.51.100.172", Client()
    monkeypatch.setattr(SshTransport, "connect", lambda self: self)
    wait_listening("10.90.0.11", 22, timeout=10, interval=0.01, via=gateway)
    with pytest.raises(TimeoutError, match="could not reach 10.90.0.11:22 within 3 s"):
        answers = iter([paramiko.SSHException("Timeout opening channel.")])
        gateway.open_tcp("10.90.0.11", 22, 3)
    answers = iter([paramiko.ChannelException(paramiko.common.OPEN_FAILED_ADMINISTRATIVELY_PROHIBITED, "denied")])
    with pytest.raises(paramiko.ChannelException):
        gateway.open_tcp("10.90.0.11", 22, 3)


# -- what a cloud clone's user-data gives the SSH transport ----------------------------------------


def test_cloud_clone_user_data_creates_ccrps_login_user_with_the_operator_key(ccrp_home, tmp_path):
    import yaml

    from ccrp_cli.ops import vpn
    from ccrp_cli.ops.clones import clone_user_data
    from ccrp_cli.fleet import Fleet, clone_view
    from ccrp_cli.providers.cloud import SSH_USER, CloudProvider
    from tests.conftest import ROOT

    fleet = Fleet.open(ROOT / "inventories" / "openstack.yaml")
    vpn.init(fleet)
    view = clone_view(fleet, fleet.load_allocated(), "nao1")
    provider = CloudProvider(fleet.inventory, tmp_path / "store")
    data = yaml.safe_load(clone_user_data(view, provider, bare=False))
    # ccrp's own login user, the one SSH_USER names, on every cloud; the image's default user (admin,
    # debian...) is not created, and no key goes anywhere but to that user.
    login = data["users"][0]
    assert login == {"name": SSH_USER, "shell": "/bin/bash", "sudo": "ALL=(ALL) NOPASSWD:ALL", "lock_passwd": True,
                     "ssh_authorized_keys": [provider.operator_public_key()]}
    assert SSH_USER == "ccrp" and "default" not in data["users"] and "ssh_authorized_keys" not in data

    class DockerLike:  # no operator key: its transport is the Docker API
        kind = "docker"

        def login_keys(self) -> None:
            return None

    data = yaml.safe_load(clone_user_data(view, DockerLike(), bare=False))
    assert all(isinstance(u, dict) and u.get("system") for u in data["users"]), data["users"]  # no login user
    assert "ssh_authorized_keys" not in data
