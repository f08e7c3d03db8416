"""What the backends whose clones are reached over SSH (openstack, gcp, aws, libvirt) share: the
operator SSH key, host-key pinning from the console output, secrets pushed over SSH, and calls
wrapped by retry.call.

A backend's provider subclasses CloudProvider (a base.Composed: it names its images and owned
modules) and implements the primitives marked `cloud:`; its transport (SshClones: exec,
push_files) and wait_ready then work the same way on every backend.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, cast

from ..errors import CcrpError
from ..models.inventory import Inventory
from ..models.layout import LOGIN_USER
from ..retry import Backoff, ErrorClass, call
from .base import GATEWAY, CloneRecord, Composed, autostop_note, wait_cloud_init

if TYPE_CHECKING:
    from ..transport.ssh import SshTransport

# The login on every cloud clone: the clone's user-data creates it with the operator key
# (render/cloudinit.py login_user), whatever user the base image has of its own.
SSH_USER = LOGIN_USER
# Trust on first use when the console shows no host keys: only when asked for explicitly.
TOFU_ENV = "CCRP_SSH_TOFU"
CONSOLE_POLL = 5.0  # seconds between console reads while an instance boots
TOFU_CONSOLE_WAIT = 180.0  # with TOFU allowed, how long the console gets to show the keys first


def operator_public_key(workdir: Path, fleet: str) -> str:
    """The fleet's operator key, created on first use (0600 in the fleet store; only the public half
    leaves): "ssh-ed25519 AAAA... ccrp-<fleet>"."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519

    from ..store import atomic_write, ensure_dir

    key_path = workdir / "ssh" / "id_ed25519"
    if not key_path.exists():
        ensure_dir(key_path.parent)
        key = ed25519.Ed25519PrivateKey.generate()
        atomic_write(key_path, key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()))
    loaded = serialization.load_ssh_private_key(key_path.read_bytes(), password=None)
    pub = loaded.public_key().public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH)
    return f"{pub.decode()} ccrp-{fleet}"


class CloudProvider(Composed):
    kind = "cloud"
    backoff = Backoff()
    # `fleet up` creates this many clones at once: cloud calls wait on the API, not on this host's
    # CPU, so a wide pool keeps 100 clones near one clone's time (bench/provision_clouds.py): 64
    # make 100 clones in two waves of one clone's chain of calls (32 took four). Throttled calls
    # are retried with backoff (retry.py), so a cloud's API rate limits slow a wave, never fail it.
    max_parallel = 64

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        # workdir = the fleet's store root (.ccrp/<fleet>): operator SSH key, pinned host keys.
        self.inv, self.fleet, self.workdir = inv, inv.fleet, Path(workdir)
        self.trust_on_first_use = os.environ.get(TOFU_ENV, "") == "1"
        self.transport = SshClones(self)

    # -- operator SSH key (ed25519, 0600 in the fleet store; only the public half leaves) ----------
    @property
    def ssh_key_path(self) -> Path:
        return self.workdir / "ssh" / "id_ed25519"

    def operator_public_key(self) -> str:
        return operator_public_key(self.workdir, self.fleet)

    def login_keys(self) -> list[str]:
        return [self.operator_public_key()]

    def resolve_image(self, image: str) -> str:
        return image  # clouds that name images indirectly override this

    # -- retries (one place) -----------------------------------------------------------------
    def classify_error(self, exc: BaseException) -> ErrorClass:  # cloud: per SDK
        raise NotImplementedError

    def api(self, what: str, fn, *args, classify=None, **kwargs):
        """Every SDK call goes through here: retried on throttling / 5xx, classified otherwise."""
        return call(fn, *args, classify=classify or self.classify_error, what=what, backoff=self.backoff, **kwargs)

    # -- cloud primitives: each cloud implements the rest of base.Provider (bootstrap,
    # run_instance, query, terminate, snapshots, teardown, list_owned/delete_owned) and this one,
    # which the shared SSH code below needs.
    def query(self) -> dict[str, CloneRecord]:  # cloud: base.Provider's
        raise NotImplementedError

    def console_output(self, robot: str) -> str:
        """The instance's serial console text (cloud-init prints the SSH host keys there)."""
        raise NotImplementedError

    def stop_note(self, robot: str) -> str | None:
        # The agent's line stays in the console log of the stopped instance.
        try:
            return autostop_note(self.console_output(robot) or "")
        except CcrpError:
            return None

    # -- shared: SSH transport (transport/ssh.py) ------------------------------------------------
    @property
    def known_hosts_path(self) -> Path:
        return self.workdir / "known_hosts"

    def gateway(self) -> CloneRecord | None:  # cloud: with Ability.ENTRY_GATEWAY
        """The fleet's entry gateway (base.Gateways)."""
        raise CcrpError(f"the {self.kind} backend makes no entry gateway")

    def _find(self, robot: str) -> CloneRecord | None:
        return self.gateway() if robot == GATEWAY else self.query().get(robot)

    def behind_gateway(self, rec: CloneRecord) -> bool:
        """A clone of a fleet with an entry gateway has no public address: SSH reaches its common
        address through the gateway (ProxyJump). What has one (the gateway, a bake's builder) is dialled."""
        return not rec.public_ip and self.inv.provider.entry == "gateway" and rec.robot != GATEWAY

    def ssh_address(self, rec: CloneRecord) -> str | None:
        return rec.common_ip if self.behind_gateway(rec) else rec.public_ip

    def _clone(self, robot: str) -> CloneRecord:
        rec = self._find(robot)
        if rec is None:
            raise CcrpError(f"no {self.kind} instance for robot {robot!r}", hint=f"ccrp clone create --robot {robot}")
        if not self.ssh_address(rec):
            raise CcrpError(f"the instance of robot {robot!r} ({rec.provider_id}) has no public IP yet")
        return rec

    def _wait_for_host_keys(self, robot: str, deadline: float) -> tuple[CloneRecord, frozenset[str]]:
        """Poll the serial console until cloud-init has printed the host keys (and the instance
        has its public IP). With TOFU allowed, give up on the console after TOFU_CONSOLE_WAIT."""
        from ..transport.ssh import fingerprints_from_console

        from ..retry import PollTimeout, poll

        give_up = min(deadline, time.monotonic() + TOFU_CONSOLE_WAIT) if self.trust_on_first_use else deadline

        def keys_shown() -> tuple[bool, tuple[CloneRecord | None, frozenset[str]]]:
            rec = self._find(robot)
            pins = fingerprints_from_console(self.console_output(robot) or "") if rec else frozenset()
            return bool(pins and rec is not None and self.ssh_address(rec)), (rec, pins)

        rec: CloneRecord | None
        try:
            rec, pins = poll(keys_shown, timeout=max(0.0, give_up - time.monotonic()), interval=CONSOLE_POLL)
            if rec is not None:  # always, once keys_shown is done
                return rec, pins
        except PollTimeout as late:
            rec = cast("tuple[CloneRecord | None, frozenset[str]]", late.last)[0]  # keys_shown's last answer
        if self.trust_on_first_use and rec is not None and self.ssh_address(rec):
            return rec, frozenset()
        why = ("not found" if rec is None else "no public IP" if not self.ssh_address(rec)
               else "cloud-init printed no SSH host keys on its console")
        raise CcrpError(
            f"{self.kind} instance of robot {robot!r}: {why} in time",
            hint=f"check the instance's console log; set {TOFU_ENV}=1 to trust its SSH key on first use instead",
        )

    def close(self) -> None:
        self.transport.close()

    def timeout_scale(self, robot: str) -> int:
        """How many times longer than on a cloud a command on this robot's clone may take (libvirt
        without KVM emulates the CPU)."""
        return 1

    def wait_ready(self, robot: str, timeout: float = 600) -> None:
        """Until cloud-init has finished on the instance: pin its host keys from the console (unless
        known_hosts has them under its instance id), SSH in, wait for cloud-init's result."""
        from ..transport.ssh import SSH_PORT, KnownHosts, wait_listening

        timeout *= self.timeout_scale(robot)  # a cloud that emulates the CPU boots its guests slowly
        deadline = time.monotonic() + timeout
        rec = self._find(robot)
        address = self.ssh_address(rec) if rec is not None else None
        if rec is not None and address and KnownHosts(self.known_hosts_path).keys(rec.provider_id):
            # A server started again: its keys are known, its sshd answers once it has booted.
            via = self.transport.session(GATEWAY) if self.behind_gateway(rec) else None
            wait_listening(address, SSH_PORT, max(1.0, deadline - time.monotonic()), CONSOLE_POLL, via=via)
            ssh = self.transport.session(robot, rec)
        else:
            rec, pins = self._wait_for_host_keys(robot, deadline)
            ssh = self.transport.session(robot, rec, pins)

        def run(argv: list[str]) -> tuple[int, str]:
            left = max(1, math.ceil(deadline - time.monotonic()))
            return ssh.exec([*ssh.sudo, "timeout", str(left), *argv], timeout=left + 30)
        wait_cloud_init(robot, run, timeout)

    def connect(self, robot: str, rec: CloneRecord, timeout: float = 300) -> None:
        """Open the SSH session to an instance query() does not list as a clone (the builder of
        `snapshot bake`), from the record run_instance returned: its host keys pinned from its
        console, as a clone's. The transport then reaches it by `robot` while it stays up."""
        from ..retry import PollTimeout, poll
        from ..transport.ssh import fingerprints_from_console

        if not rec.public_ip:
            raise CcrpError(f"the {self.kind} instance {rec.provider_id} has no public IP to log in over")

        def keys_shown() -> tuple[bool, frozenset[str]]:
            pins = fingerprints_from_console(self.console_output(robot) or "")
            return bool(pins), pins

        try:
            pins = poll(keys_shown, timeout=timeout, interval=CONSOLE_POLL)
        except PollTimeout:
            if not self.trust_on_first_use:
                raise CcrpError(f"{self.kind} instance {rec.provider_id}: cloud-init printed no SSH host keys on its "
                                "console in time", hint=f"set {TOFU_ENV}=1 to trust its SSH key on first use") from None
            pins = frozenset()
        self.transport.session(robot, rec, pins)


class SshClones:
    """The clouds' transport (base.Transport): one SSH session per robot (transport/ssh.py), opened
    on first use with the host keys pinned from the instance's console, reused while it stays up."""

    def __init__(self, provider: CloudProvider) -> None:
        # The provider finds the instance (query), its console (the keys to pin) and the operator key.
        self.provider = provider
        self._ssh: dict[str, SshTransport] = {}  # robot -> live session
        self._lock = threading.Lock()
        self._robot_locks: dict[str, threading.Lock] = {}

    def session(self, robot: str, rec: CloneRecord | None = None, pins: frozenset[str] | None = None):
        """The robot's SSH connection, opened on first use and reused while it stays up. Keys not
        in known_hosts yet are pinned from the console output."""
        from ..transport.ssh import KnownHosts, SshTransport, fingerprints_from_console

        p = self.provider
        with self._lock:
            lock = self._robot_locks.setdefault(robot, threading.Lock())
        with lock:
            ssh = self._ssh.get(robot)
            if ssh is not None and ssh.active and (rec is None or (ssh.host, ssh.alias) == (p.ssh_address(rec), rec.provider_id)):
                return ssh
            if ssh is not None:
                ssh.close()
            rec = rec or p._clone(robot)
            known = KnownHosts(p.known_hosts_path)
            if pins is None:
                pins = frozenset() if known.keys(rec.provider_id) else fingerprints_from_console(p.console_output(robot) or "")
            p.operator_public_key()  # creates the key on first use
            # The gateway's session (its own lock), shared by every clone behind it.
            via = self.session(GATEWAY) if p.behind_gateway(rec) else None
            address = p.ssh_address(rec)
            if address is None:
                raise CcrpError(f"the instance of robot {robot!r} ({rec.provider_id}) has no address to reach yet")
            ssh = SshTransport(address, SSH_USER, p.ssh_key_path, pins, known_hosts=known,
                               host_alias=rec.provider_id, trust_on_first_use=p.trust_on_first_use, via=via).connect()
            self._ssh[robot] = ssh
            return ssh

    def forget(self, robot: str) -> None:
        """Close the robot's session (its clone is going down)."""
        with self._lock:
            ssh = self._ssh.pop(robot, None)
        if ssh is not None:
            ssh.close()

    def close(self) -> None:
        """Close every SSH connection opened."""
        with self._lock:
            sessions, self._ssh = list(self._ssh.values()), {}
        for ssh in sessions:
            ssh.close()

    def _run(self, robot: str, fn):
        """fn(session); once more on a fresh connection if the cached one broke before starting."""
        from ..transport.ssh import ChannelOpenError

        try:
            return fn(self.session(robot))
        except ChannelOpenError:
            return fn(self.session(robot))

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        """argv as root on the clone (like a command in the Docker clone), ended by `timeout`."""
        timeout *= self.provider.timeout_scale(robot)
        limit = str(max(1, math.ceil(timeout)))
        return self._run(robot, lambda ssh: ssh.exec([*ssh.sudo, "timeout", limit, *argv], timeout=timeout + 30))

    def push_files(self, robot: str, files: Sequence, restart: Sequence[str] = ()) -> None:
        def push(ssh) -> None:
            ssh.put_files(files)
            if restart:  # one job each, ordered by their units (the graph keeper after OpenVPN)
                ssh.check([*ssh.sudo, "systemctl", "restart", *restart], timeout=120)

        self._run(robot, push)
