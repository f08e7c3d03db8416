"""Clone lifecycle on any provider: create (idempotent), configure, check, delete.

Commands hold the fleet lock; per-robot work may run in threads, so state updates go through
StateWriter, which serialises them and saves atomically after each change.
"""

from __future__ import annotations

import hashlib
import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .errors import CcrpError
from .fleet import Fleet, clone_view
from .models.names import clone_host
from .models.state import FleetState
from .pki.store import RobotRevoked
from .providers.base import CloneSpec, CloneState, Provider

Progress = Callable[[str], None]
HEALTH_SCRIPT = (Path(__file__).parent / "agent" / "health.py").read_text


class StateWriter:
    """Thread-safe read-modify-save of the fleet state (the caller holds the fleet lock)."""

    def __init__(self, fleet: Fleet, state: FleetState) -> None:
        self.fleet, self.state, self.lock = fleet, state, threading.Lock()

    def update(self, robot: str, **fields) -> None:
        with self.lock:
            rec = self.state.robots[robot]
            for k, v in fields.items():
                setattr(rec, k, v)
            self.fleet.store.save_state(self.state)


def snapshot_image(state: FleetState) -> str:
    if not state.snapshot or not state.snapshot.get("image"):
        raise CcrpError("the fleet has no snapshot to create clones from", hint="run `ccrp snapshot build -i INVENTORY`")
    return state.snapshot["image"]


@dataclass
class CloneResult:
    robot: str
    action: str  # created | reused | deleted | absent | failed
    detail: str = ""
    seconds: float = 0.0

    def row(self) -> tuple:
        return (self.robot, self.action, f"{self.seconds:.1f}s", self.detail)


def health(provider: Provider, robot: str) -> dict:
    rc, out = provider.exec(robot, ["python3", "-c", HEALTH_SCRIPT()], timeout=20)
    try:
        return json.loads(out.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"vpn": {"up": False, "clients": []}, "master": {"reachable": False, "nodes": {}}, "error": out[-200:]}


def remote_digests(provider: Provider, robot: str, files: list) -> dict[str, str]:
    """path -> sha256 of those of `files` that the clone holds (a missing one is left out)."""
    _, out = provider.exec(robot, ["sha256sum", *(f.dest for f in files)], timeout=20)
    return {line.split()[1]: line.split()[0] for line in out.splitlines() if len(line.split()) == 2}


def same(have: dict[str, str], files: list) -> bool:
    return all(have.get(f.dest) == hashlib.sha256(f.content.encode()).hexdigest() for f in files)


def files_current(provider: Provider, robot: str, files: list) -> bool:
    """True when the clone already holds exactly these files: re-running `fleet up` then leaves
    OpenVPN (and the robot's live session) and the relay alone."""
    return same(remote_digests(provider, robot, files), files)


def applied_marker(files: list):
    """The file pushed after `files` once their groups are set and the units restarted. A run
    killed between copying the files and restarting OpenVPN (which starts only when its key is
    there) leaves files that match and a server that never started: without the marker the next
    run took them for done, and the clone failed `not serving` on every run after."""
    from .render.bundles import BundleFile
    from .render.view import SECRETS_DIR

    listing = "".join(f"{f.dest} {f.group} {f.mode:o} {hashlib.sha256(f.content.encode()).hexdigest()}\n" for f in files)
    return BundleFile(".applied", hashlib.sha256(listing.encode()).hexdigest() + "\n", 0o600, f"{SECRETS_DIR}/.applied")


# Hands the secrets directory to the openvpn group ($1 = mode) and prints the device of / and of
# the directory: they must differ, or the keys would land on the disk that snapshots capture.
SECRETS_DIR_SH = 'install -d -m "$1" -o root -g openvpn "$0" && stat -c %d / "$0"'


def prepare_secrets_dir(provider: Provider, robot: str) -> None:
    from .render.view import SECRETS_DIR

    # 0751: the relay's user opens relay.key by name but cannot list the directory.
    rc, out = provider.exec(robot, ["sh", "-c", SECRETS_DIR_SH, SECRETS_DIR, "0751"], timeout=30)
    devices = out.split()[-2:]  # after anything sudo may warn about first
    if rc != 0 or len(devices) != 2 or not all(d.isdigit() for d in devices):
        raise CcrpError(f"cannot prepare {SECRETS_DIR} on {clone_host(robot)}: {out.strip()[-200:]}")
    if devices[0] == devices[1]:
        raise CcrpError(
            f"refusing to push secrets to {clone_host(robot)}: {SECRETS_DIR} is on its root disk, where a snapshot "
            "would capture them",
            hint=f"the clone's user-data mounts a tmpfs there at boot; recreate the clone: ccrp clone delete -i INVENTORY "
                 f"--robot {robot}, then ccrp clone create -i INVENTORY --robot {robot}",
        )


def kill_session(provider: Provider, robot: str) -> None:
    """End the robot's live VPN session (management interface `kill <cn>`)."""
    rc, out = provider.exec(robot, ["python3", "-c", HEALTH_SCRIPT(), "kill", robot], timeout=20)
    if rc != 0:
        raise CcrpError(f"cannot end the VPN session on {clone_host(robot)}: {out.strip()[-200:]}")


# Waits inside the clone with a shell loop (cheap) instead of a python health probe per poll:
# with many clones booting at once, the probes' own CPU was what slowed every boot down.
WAIT_SERVING_SH = 'until [ -S "$0" ] && ss -Hltn "sport = :$1" | grep -q .; do sleep 0.2; done'


def wait_serving(provider: Provider, robot: str, master_port: int, timeout: float = 60) -> dict:
    """Until the VPN server runs and the ROS master answers inside the clone."""
    from .render.view import MGMT_SOCKET

    from .retry import PollTimeout, poll

    deadline = time.monotonic() + timeout
    provider.exec(robot, ["sh", "-c", WAIT_SERVING_SH, MGMT_SOCKET, str(master_port)], timeout=timeout)

    def serving() -> tuple[bool, dict]:
        h = health(provider, robot)
        return h["vpn"]["up"] and h["master"]["reachable"], h

    try:
        return poll(serving, timeout=max(0.0, deadline - time.monotonic()), interval=0.5)
    except PollTimeout as late:
        raise CcrpError(f"clone {clone_host(robot)} is not serving after {timeout:.0f} s: {json.dumps(late.last)[:300]}") from None


def clone_user_data(view, provider: Provider, bare: bool) -> str:
    """A cloud clone gets ccrp's login user (render/view.py LOGIN_USER) with the fleet's operator key:
    the SSH transport logs in as it. A Docker clone has no login user; its transport is the Docker API."""
    from .render import cloudinit

    return cloudinit.user_data(view, login_keys=provider.login_keys(), install_packages=bare)


def ensure_clone(fleet: Fleet, provider: Provider, writer: StateWriter, robot: str, progress: Progress) -> CloneResult:
    """Create or reuse the clone of `robot`, push its secrets, wait until it serves."""
    from .render import bundles
    from .render.limits import fit_user_data

    t0 = time.monotonic()
    state = writer.state
    view = clone_view(fleet, state, robot)
    # Clones are ensured in parallel threads and issue_robot is a read-modify-write of the PKI
    # index: serialise it, or one thread's certificates vanish from the index.
    with writer.lock:
        try:
            fleet.pki.issue_robot(robot, fleet.inventory.vpn.cert_days)
        except RobotRevoked as revoked:
            return _left_revoked(fleet, provider, writer, robot, revoked, progress)
        fleet.pki.issue_relay(robot, str(view.addr.common_ip), fleet.inventory.vpn.cert_days)
    # A bare snapshot gets the recipe's packages from cloud-init at first boot.
    bare = bool(state.snapshot and state.snapshot.get("bare"))
    user_data = clone_user_data(view, provider, bare)
    fit_user_data(provider.kind, user_data)
    image = snapshot_image(state)
    rec = state.robots[robot]
    writer.update(robot, phase="creating")
    spec = CloneSpec(
        robot=robot, hostname=view.addr.clone_host, image=image, user_data=user_data,
        instance_id=f"{fleet.name}-{robot}-{rec.index}", common_ip=str(view.addr.common_ip),
        vpn_subnet=str(view.addr.vpn_subnet),
    )
    progress(f"[{robot}] clone {view.addr.clone_host}: starting from {image}")
    record = provider.run_instance(spec)
    try:
        provider.wait_ready(robot, timeout=1200 if bare else 300)
        secrets = bundles.clone_secrets(view, fleet.pki.credentials(robot))
        keys = [f for f in secrets if f.name != "crl.pem"]
        crl = [f for f in secrets if f.name == "crl.pem"]
        applied = applied_marker(keys)
        have = remote_digests(provider, robot, [*secrets, applied])
        if not same(have, [*keys, applied]):
            prepare_secrets_dir(provider, robot)
            provider.push_files(robot, secrets, restart=["ccrp-openvpn.service", "ccrp-relay.service"])
            provider.push_files(robot, [applied])  # last: until it is there, the next run pushes again
        elif not same(have, crl):
            # Only the CRL changed (another robot was revoked): OpenVPN re-reads it, the robot's
            # live session stays.
            provider.push_files(robot, crl, restart=[])
        wait_serving(provider, robot, fleet.inventory.ros.master_port)
        push_relay_config(fleet, provider, state, robot)
    except BaseException:
        writer.update(robot, phase="failed", provider_id=record.provider_id)
        if record.created:
            provider.terminate(robot)  # roll back only what this attempt created
        raise
    endpoint = record.public_ip
    writer.update(
        robot, phase="ready", provider_id=record.provider_id, public_endpoint=endpoint,
        addresses={"public": endpoint or "", "common": str(view.addr.common_ip),
                   "vpn": str(view.addr.clone_vpn_ip), "robot_vpn": str(view.addr.robot_vpn_ip)},
    )
    took = time.monotonic() - t0
    progress(f"[{robot}] clone {view.addr.clone_host} ready in {took:.1f}s ({endpoint})")
    return CloneResult(robot, "created" if record.created else "reused", endpoint or "", took)


def _left_revoked(fleet: Fleet, provider: Provider, writer: StateWriter, robot: str, revoked: CcrpError,
                  progress: Progress) -> CloneResult:
    """A revoked robot stays unenrolled: no certificate, no clone created or configured. A clone
    of it that runs gets the current CRL and the kill again, in case `vpn revoke` could not reach
    it: a failed TLS renegotiation alone does not end a session (docs/security.md)."""
    from .render.bundles import crl_file

    writer.state.robots[robot].phase = "revoked"
    writer.fleet.store.save_state(writer.state)  # the caller holds writer.lock
    rec = provider.query().get(robot)
    if rec is not None and rec.state is CloneState.RUNNING:
        provider.push_files(robot, [crl_file(fleet.pki.crl_path.read_text())], restart=[])
        kill_session(provider, robot)
    progress(f"[{robot}] {revoked.message}")
    return CloneResult(robot, "revoked", revoked.message + f" ({revoked.hint})")


def push_relay_config(fleet: Fleet, provider: Provider, state: FleetState, robot: str) -> bool:
    """Give robot's clone its current relay.json; the agent picks it up without a restart.
    Returns True when the file changed."""
    from .render.bundles import BundleFile
    from .render.view import CCRP_ETC
    from .sharing import relay_config_text

    files = [BundleFile("relay.json", relay_config_text(fleet, state, robot), 0o644, f"{CCRP_ETC}/relay.json")]
    if files_current(provider, robot, files):
        return False
    provider.push_files(robot, files, restart=[])
    return True


def delete_clone(fleet: Fleet, provider: Provider, writer: StateWriter, robot: str, forget: bool) -> CloneResult:
    t0 = time.monotonic()
    if robot in writer.state.robots:
        writer.update(robot, phase="deleting")
    provider.terminate(robot)  # the clone and its secrets volume
    with writer.lock:
        if forget:
            writer.state.robots.pop(robot, None)
        elif robot in writer.state.robots:
            writer.state.robots[robot].clear_clone()
        fleet.store.save_state(writer.state)
    return CloneResult(robot, "deleted", "", time.monotonic() - t0)
