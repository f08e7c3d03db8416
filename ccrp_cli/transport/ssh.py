"""SSH to a cloud clone (paramiko, imported lazily) with its host key pinned.

A host key is accepted when, in this order:
  1. known_hosts in the fleet store holds it under the host's alias (the instance id, so a public
     IP the cloud hands to a new instance never inherits the old instance's key);
  2. its SHA256 fingerprint is among those cloud-init printed on the instance's serial console
     (`fingerprints_from_console`); it is then recorded in known_hosts;
  3. trust on first use was asked for explicitly: accepted with a printed warning, recorded.
Anything else is refused before authentication, so no command ever runs on an unverified host.
Never paramiko's AutoAddPolicy.
"""

from __future__ import annotations

import base64
import errno
import hashlib
import re
import shlex
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterable

from ..errors import CcrpError, printable
from ..retry import Backoff, ErrorClass, call
from . import EXEC_OUTPUT_MAX, too_much

FP_BEGIN, FP_END = "-----BEGIN SSH HOST KEY FINGERPRINTS-----", "-----END SSH HOST KEY FINGERPRINTS-----"
KEYS_BEGIN, KEYS_END = "-----BEGIN SSH HOST KEY KEYS-----", "-----END SSH HOST KEY KEYS-----"
# "256 SHA256:<43 base64 chars> root@host (ED25519)", after whatever prefix the console adds
# ("ec2: ", "[   12.3] cloud-init[812]: "). MD5 fingerprints (old cloud-init) are not trusted.
_FP_LINE = re.compile(r"\b\d+\s+(SHA256:[A-Za-z0-9+/]{43})=?\s.*\([A-Z0-9-]+\)\s*$")
_KEY_LINE = re.compile(r"\b((?:ssh|ecdsa-sha2|sk-ssh|sk-ecdsa-sha2)-[a-z0-9@.-]+)\s+([A-Za-z0-9+/]+={0,2})(?:\s|$)")

# Connecting while a VM boots: refused until sshd listens, timeouts until the network is up.
CONNECT_BACKOFF = Backoff(attempts=10, base=0.5, cap=5.0)
SSH_PORT = 22
# put_files' installs: groups of four arguments (mode, group, staged file, destination).
INSTALL_EACH = 'while [ "$#" -gt 0 ]; do install -m "$1" -o root -g "$2" "$3" "$4" || exit; shift 4; done'


def fingerprint(key_blob: bytes) -> str:
    """OpenSSH's SHA256 fingerprint of a public key blob ("SHA256:" + unpadded base64)."""
    return "SHA256:" + base64.b64encode(hashlib.sha256(key_blob).digest()).decode().rstrip("=")


def _last_block(lines: list[str], begin: str, end: str) -> list[str]:
    """Lines of the last complete begin..end block (a console may hold several boots)."""
    block: list[str] | None = None
    last: list[str] = []
    for line in lines:
        if begin in line:
            block = []
        elif end in line:
            if block is not None:
                last = block
            block = None
        elif block is not None:
            block.append(line)
    return last


def fingerprints_from_console(text: str) -> frozenset[str]:
    """SHA256 fingerprints of the host keys cloud-init printed on the serial console: from the
    FINGERPRINTS block, and computed from the full keys of the KEYS block. Empty when neither
    block is complete yet (cloud-init prints them at the end of its final stage)."""
    lines = text.replace("\r", "").split("\n")
    found = set()
    for line in _last_block(lines, FP_BEGIN, FP_END):
        m = _FP_LINE.search(line)
        if m:
            found.add(m.group(1))
    for line in _last_block(lines, KEYS_BEGIN, KEYS_END):
        m = _KEY_LINE.search(line)
        if m:
            try:
                found.add(fingerprint(base64.b64decode(m.group(2), validate=True)))
            except ValueError:
                continue  # a garbled line on a noisy console: the fingerprints block still counts
    return frozenset(found)


def _stderr_warning(message: str) -> None:
    print(printable(f"ccrp: warning: {message}"), file=sys.stderr, flush=True)  # it names what a server sent


class KnownHosts:
    """known_hosts (OpenSSH format, 0600) in the fleet store; entries are keyed by a host alias.

    `ssh -o UserKnownHostsFile=<file> -o HostKeyAlias=<alias> ccrp@<ip>` uses the same file."""

    _lock = threading.Lock()  # threads of one run (fleet up fan-out) record keys concurrently

    def __init__(self, path: Path) -> None:
        self.path = Path(path)

    def _entries(self) -> list[tuple[str, str, str]]:
        if not self.path.exists():
            return []
        out = []
        for line in self.path.read_text().splitlines():
            parts = line.split()
            if len(parts) >= 3 and not line.startswith("#"):
                out.append((parts[0], parts[1], parts[2]))
        return out

    def keys(self, alias: str) -> list[tuple[str, str]]:
        return [(t, b64) for a, t, b64 in self._entries() if a == alias]

    def _rewrite(self, entries: list[tuple[str, str, str]]) -> None:
        from ..store import atomic_write

        atomic_write(self.path, "".join(f"{a} {t} {b64}\n" for a, t, b64 in entries))

    def add(self, alias: str, key_type: str, b64: str) -> None:
        with self._lock:
            entries = [e for e in self._entries() if e[:2] != (alias, key_type)]
            self._rewrite(entries + [(alias, key_type, b64)])


class PinnedHostKeyPolicy:
    """paramiko MissingHostKeyPolicy (duck-typed: paramiko only calls missing_host_key) for a host
    that known_hosts does not know yet: accept only a pinned fingerprint, or TOFU if asked."""

    def __init__(self, host: str, pinned: Iterable[str], known_hosts: KnownHosts | None = None,
                 alias: str | None = None, trust_on_first_use: bool = False,
                 warn: Callable[[str], None] = _stderr_warning) -> None:
        self.host, self.pinned = host, frozenset(pinned)
        self.known_hosts, self.alias = known_hosts, alias or host
        self.trust_on_first_use, self.warn = trust_on_first_use, warn

    def missing_host_key(self, client, hostname: str, key) -> None:
        fp = fingerprint(key.asbytes())
        if fp not in self.pinned:
            if self.pinned:
                raise CcrpError(
                    f"host key of {self.host} is {fp} ({key.get_name()}), not one of the fingerprints "
                    f"pinned from its console ({', '.join(sorted(self.pinned))})",
                    hint="this is not the instance ccrp created, or something intercepts SSH: nothing was sent",
                )
            if not self.trust_on_first_use:
                raise CcrpError(
                    f"no pinned host key for {self.host}: refusing its key {fp} ({key.get_name()})",
                    hint="wait until cloud-init prints the host keys on the console, or allow trust on first "
                         "use explicitly (CCRP_SSH_TOFU=1)",
                )
            self.warn(f"trusting the host key of {self.host} on first use: {fp} ({key.get_name()}); it was "
                      f"not verified against the console"
                      + (f" and is recorded in {self.known_hosts.path}" if self.known_hosts else ""))
        # The caller's client accepts it for this connection; known_hosts for the next ones.
        client.get_host_keys().add(hostname, key.get_name(), key)
        if self.known_hosts:
            self.known_hosts.add(self.alias, key.get_name(), key.get_base64())


def _booting(exc: BaseException) -> bool:
    """What connecting to a guest that is still booting gives: refused until sshd listens, timeouts
    until its network is up, "no route to host" while the cloud's router gets no ARP answer for it
    (a started OpenStack server, seen on a real Nova)."""
    return isinstance(exc, (ConnectionRefusedError, TimeoutError)) or (
        isinstance(exc, OSError) and exc.errno == errno.EHOSTUNREACH)


def classify_connect(exc: BaseException) -> ErrorClass:
    """Only a guest still booting is worth another try."""
    from paramiko.ssh_exception import NoValidConnectionsError, SSHException

    if isinstance(exc, NoValidConnectionsError):
        return ErrorClass.RETRYABLE if all(_booting(e) for e in exc.errors.values()) else ErrorClass.FATAL
    if _booting(exc):
        return ErrorClass.RETRYABLE
    if isinstance(exc, SSHException) and isinstance(exc.__context__, TimeoutError):
        return ErrorClass.RETRYABLE  # "Error reading SSH protocol banner": a read that timed out
    if isinstance(exc, SSHException) and str(exc) == "No existing session":
        # The server closed the connection after the key exchange, before authentication ended: sshd
        # restarting while the clone boots (seen on a libvirt VM under TCG and load). A refused key
        # is AuthenticationException, a changed host key BadHostKeyException: both stay fatal.
        return ErrorClass.RETRYABLE
    return ErrorClass.FATAL


def wait_listening(host: str, port: int, timeout: float, interval: float = 5.0, via: "SshTransport | None" = None) -> None:
    """Until something accepts TCP connections on host:port (from the jump host `via`, when given),
    for a guest that boots for minutes (a started cloud server under emulation): the SSH connect's
    own retries cover seconds. An error other than a booting guest's is left to the SSH connect
    that follows, which names it."""
    import socket

    from ..retry import PollTimeout, poll

    def accepts() -> tuple[bool, None]:
        wait = min(10.0, interval * 2)
        try:
            with (via.open_tcp(host, port, wait) if via else socket.create_connection((host, port), timeout=wait)):
                return True, None
        except OSError as exc:
            return not _booting(exc), None
    try:
        poll(accepts, timeout=timeout, interval=interval)
    except PollTimeout:
        raise CcrpError(f"SSH to {host}:{port} did not answer within {timeout:.0f} s",
                        hint="the instance may not have booted: read its console log") from None


class ChannelOpenError(CcrpError):
    """The connection broke before a command started: safe to reconnect and run it again."""


class SshTransport:
    """One SSH connection to `user@host`, authenticated with the operator key; with `via`, through
    that connection (OpenSSH's ProxyJump: a direct-tcpip channel from the jump host to host:port).
    The jump host's key and this host's are each pinned on their own: the jump host only carries
    bytes it cannot read."""

    def __init__(self, host: str, user: str, key_path: Path, pinned_host_keys: Iterable[str] = (), *,
                 port: int = SSH_PORT, known_hosts: KnownHosts | None = None, host_alias: str | None = None,
                 trust_on_first_use: bool = False, connect_timeout: float = 10.0,
                 backoff: Backoff = CONNECT_BACKOFF, warn: Callable[[str], None] = _stderr_warning,
                 via: "SshTransport | None" = None) -> None:
        self.host, self.user, self.key_path, self.port, self.via = host, user, Path(key_path), port, via
        self.known_hosts, self.alias = known_hosts, host_alias or host
        self.policy = PinnedHostKeyPolicy(host, pinned_host_keys, known_hosts, self.alias, trust_on_first_use, warn)
        self.connect_timeout, self.backoff = connect_timeout, backoff
        # Root's files are installed through sudo unless we log in as root.
        self.sudo = [] if user == "root" else ["sudo", "-n"]
        self._client = None

    @property
    def where(self) -> str:
        here = f"{self.user}@{self.host}" + (f":{self.port}" if self.port != SSH_PORT else "")
        return here + (f" via {self.via.where}" if self.via else "")

    def open_tcp(self, host: str, port: int, timeout: float):
        """A channel from this host to host:port (OpenSSH's direct-tcpip, what ProxyJump runs over).
        The target refusing or not answering yet (a clone booting behind the gateway) comes back as
        the ConnectionRefusedError or TimeoutError a direct connection would give, so it is retried
        alike."""
        import paramiko

        transport = self.connect()._client.get_transport()
        try:
            return transport.open_channel("direct-tcpip", (host, port), ("127.0.0.1", 0), timeout=timeout)
        except paramiko.ChannelException as exc:
            # RFC 4254's reasons: 2 is "connect failed" (refused, no route), the rest are the jump host's.
            if exc.code == paramiko.common.OPEN_FAILED_CONNECT_FAILED:
                raise ConnectionRefusedError(f"{self.host} could not reach {host}:{port}: {exc.text}") from None
            raise
        except paramiko.SSHException as exc:
            # The jump host still trying to connect when `timeout` ran out: a guest whose network is
            # not up yet answers no SYN (a started server behind the gateway on a real OpenStack:
            # `clone start` failed at once on it).
            if "Timeout opening channel" in str(exc):
                raise TimeoutError(f"{self.host} could not reach {host}:{port} within {timeout:.0f} s") from None
            # paramiko keeps one failure reason per connection: with channels opened at once through
            # the gateway (clones booting behind it), one thread's "connect failed" can be taken by
            # another, which leaves this one no reason. The jump host still up, its target refused
            # (two clones behind a real OpenStack's gateway: `fleet up` failed one of them on it).
            if str(exc) == "Unable to open channel." and transport.is_active():
                raise ConnectionRefusedError(f"{self.host} could not reach {host}:{port}") from None
            raise

    # -- connection -----------------------------------------------------------------------------
    def _connect_once(self):
        import paramiko

        client = paramiko.SSHClient()
        # paramiko looks keys up by "host" (port 22) or "[host]:port"; ours live under the alias.
        lookup = self.host if self.port == SSH_PORT else f"[{self.host}]:{self.port}"
        for key_type, b64 in self.known_hosts.keys(self.alias) if self.known_hosts else []:
            client.get_host_keys().add(lookup, key_type, paramiko.PKey.from_type_string(key_type, base64.b64decode(b64)))
        client.set_missing_host_key_policy(self.policy)
        try:
            client.connect(
                self.host, port=self.port, username=self.user, pkey=paramiko.PKey.from_path(self.key_path),
                timeout=self.connect_timeout, banner_timeout=self.connect_timeout, auth_timeout=self.connect_timeout,
                allow_agent=False, look_for_keys=False,
                sock=self.via.open_tcp(self.host, self.port, self.connect_timeout) if self.via else None,
            )
        except BaseException:
            client.close()
            raise
        return client

    def connect(self) -> "SshTransport":
        import paramiko

        if self.active:
            return self
        self.close()  # a connection that broke: start over
        try:
            self._client = call(self._connect_once, classify=classify_connect, what=f"SSH to {self.where}",
                                backoff=self.backoff)
        except CcrpError:
            raise
        except paramiko.BadHostKeyException as exc:
            raise CcrpError(
                f"host key of {self.host} changed: it offers {fingerprint(exc.key.asbytes())} ({exc.key.get_name()}) "
                f"but {self.known_hosts.path if self.known_hosts else 'known_hosts'} holds "
                f"{fingerprint(exc.expected_key.asbytes())} for {self.alias}",
                hint="nothing was sent; if the instance was really rebuilt, delete and re-create its clone",
            ) from None
        except paramiko.AuthenticationException:
            raise CcrpError(f"SSH to {self.where}: the operator key {self.key_path} was refused",
                            hint="the instance did not get the fleet's operator key (key pair / metadata)") from None
        except (paramiko.SSHException, OSError, EOFError) as exc:
            raise CcrpError(f"SSH to {self.where} failed: {type(exc).__name__}: {str(exc)[:200]}") from None
        return self

    @property
    def active(self) -> bool:
        t = self._client.get_transport() if self._client else None
        return bool(t and t.is_active())

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self) -> "SshTransport":
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    # -- commands -----------------------------------------------------------------------------------
    def exec(self, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        """Run argv (quoted with shlex.join, never a string built from names); stdout and stderr
        combined. A command still running after `timeout` is abandoned with a CcrpError."""
        import paramiko

        if isinstance(argv, str):
            raise TypeError("argv must be a list of arguments, not a shell string")
        self.connect()
        try:
            chan = self._client.get_transport().open_session(timeout=self.connect_timeout)
        except (paramiko.SSHException, OSError, EOFError, AttributeError) as exc:
            self.close()
            raise ChannelOpenError(f"SSH to {self.where}: cannot open a session ({type(exc).__name__})") from None
        deadline = time.monotonic() + timeout
        try:
            chan.set_combine_stderr(True)
            chan.exec_command(shlex.join(argv))
            out = bytearray()
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise CcrpError(f"`{shlex.join(argv)[:120]}` on {self.host} did not finish within {timeout:.0f} s")
                chan.settimeout(remaining)
                try:
                    data = chan.recv(65536)
                except TimeoutError:
                    continue
                if not data:
                    break
                out += data
                if len(out) > EXEC_OUTPUT_MAX:  # closing the channel (below) ends the command
                    raise CcrpError(too_much(shlex.join(argv), self.host))
            # The exit status follows the end of output; -1 when the command died of a signal.
            if not chan.status_event.wait(max(0.0, deadline - time.monotonic()) or 1.0):
                raise CcrpError(f"`{shlex.join(argv)[:120]}` on {self.host} sent no exit status")
            return chan.exit_status, out.decode(errors="replace")
        finally:
            chan.close()

    def check(self, argv: list[str], timeout: float = 60) -> str:
        rc, out = self.exec(argv, timeout)
        if rc != 0:
            raise CcrpError(f"`{shlex.join(argv)[:160]}` failed on {self.host} (exit {rc}): {out.strip()[-200:]}")
        return out

    def put_files(self, files: list) -> None:
        """Install bundle files (render.files.BundleFile: dest, content, mode, group) as root:
        uploaded over SFTP into a fresh 0700 directory of the login user in /dev/shm (memory: a
        key must not touch the disk even while staged), then `install -m MODE -o root -g GROUP`
        each to its destination in one sudo; the directory is removed in any case."""
        tmp = self.check(["mktemp", "-d", "/dev/shm/ccrp-push.XXXXXXXXXX"]).strip()
        if not re.fullmatch(r"/dev/shm/ccrp-push\.[A-Za-z0-9]{10}", tmp):
            raise CcrpError(f"mktemp on {self.host} returned an unexpected path: {tmp[:100]!r}")
        try:
            sftp = self._client.open_sftp()
            try:
                for i, f in enumerate(files):
                    with sftp.open(f"{tmp}/{i}", "wb") as fh:
                        fh.chmod(0o600)
                        fh.write(f.content.encode())
            finally:
                sftp.close()
            # One sudo for all: a round trip per file cost about a second on an emulated VM and a
            # network's latency each on a cloud. The script is constant, the names its arguments.
            args = [a for i, f in enumerate(files) for a in (f"{f.mode:04o}", f.group, f"{tmp}/{i}", f.dest)]
            self.check([*self.sudo, "sh", "-c", INSTALL_EACH, "sh", *args])
        finally:
            # Best effort: a failure here must not hide the one that brought us here.
            try:
                self.exec(["rm", "-rf", "--", tmp], timeout=30)
            except CcrpError:
                pass
