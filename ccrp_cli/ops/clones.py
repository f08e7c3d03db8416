"""Clone lifecycle on any provider: create (idempotent), configure, check, delete.

Commands hold the fleet lock; per-robot work may run in threads, so state updates go through
StateWriter, which serialises them and saves atomically after each change.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, cast

from ..errors import CcrpError
from ..fleet import Fleet, clone_view, snapshot_image
from ..models.layout import MGMT_SOCKET, SECRETS_DIR
from ..models.inventory import Inventory
from ..models.names import clone_host
from ..models.state import FleetState
from ..render.files import applied_marker
from ..probe import files_current, health, kill_session, remote_digests, same
from . import gateway, install_space
from ..providers.base import (
    CloneSpec,
    CloneState,
    Housekeeping,
    Lifecycle,
    Origin,
    Provider,
    Reaches,
    cloud_init_clean,
)

if TYPE_CHECKING:
    from ..render.files import BundleFile
    from ..render.view import CloneView

Progress = Callable[[str], None]


class StateWriter:
    """Thread-safe read-modify-save of the fleet state (the caller holds the fleet lock)."""

    def __init__(self, fleet: Fleet, state: FleetState) -> None:
        self.fleet, self.state, self.lock = fleet, state, threading.Lock()
        # Clones that were up when the run began: they stay in each other's relay config while
        # this run flips them to `creating` and back (see live()).
        self.ready_before = {n for n, rec in state.robots.items() if rec.phase == "ready"}
        # robot -> the relay.json this run found on (or pushed to) its clone: reshare() pushes
        # only what differs from it, without asking the clone again.
        self.relay_current: dict[str, str] = {}

    def live(self) -> set[str]:
        """Clones a relay config names as up during this run: those ready now and those ready when
        it began (a reused clone is `creating` for a moment; dropping it from its partners'
        configs then would make every no-op `fleet up` reconfigure sharing twice)."""
        return self.ready_before | {n for n, rec in list(self.state.robots.items()) if rec.phase == "ready"}

    def update(self, robot: str, **fields: object) -> None:
        with self.lock:
            rec = self.state.robots[robot]
            for k, v in fields.items():
                setattr(rec, k, v)
            self.fleet.store.save_state(self.state)


@dataclass
class CloneResult:
    robot: str
    action: str  # created | reused | deleted | absent | failed
    detail: str = ""
    seconds: float = 0.0
    origin: Origin | None = None  # what the provider did to have the clone (ensure_clone)
    sent_bytes: int | None = None  # what `ccrp deploy` pushed to the clone (its install space's part)

    def row(self) -> tuple[str, str, str, str]:
        return (self.robot, self.action, f"{self.seconds:.1f}s", self.detail)


# Hands the secrets directory to the openvpn group ($1 = mode) and prints the device of / and of
# the directory: they must differ, or the keys would land on the disk that snapshots capture.
SECRETS_DIR_SH = 'install -d -m "$1" -o root -g openvpn "$0" && stat -c %d / "$0"'


def prepare_secrets_dir(provider: Reaches, robot: str) -> None:
    # 0751: the relay's user opens relay.key by name but cannot list the directory.
    rc, out = provider.transport.exec(robot, ["sh", "-c", SECRETS_DIR_SH, SECRETS_DIR, "0751"], timeout=30)
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


def keyed_units(inv: Inventory) -> list[str]:
    """The units that wait for the keys ccrp pushes (ConditionPathExists), (re)started with them."""
    return ["ccrp-openvpn.service", "ccrp-relay.service", *(["ccrp-graph.service"] if inv.ros.ros2 else [])]


# Whether a clone serves, in bash inside it (no python start per check: with many clones booting
# at once, the probes' own CPU slowed every boot down). The VPN: ccrp-openvpn active (Type=notify:
# OpenVPN said it is ready) and listening on its management socket. The master: an XML-RPC
# getPid answered with code 1, over bash's /dev/tcp. A ROS 2 clone ($PORT is `ros2`) has no master:
# there "master" means its ROS 2 environment works: ccrp-graph.service listens (its node has
# started in the robot's domain), or on a clone without that service (an older ccrp's), ros2_graph.py
# check did as the ros user, asked once the VPN serves and then remembered for this boot in /run (a
# python start with the ROS libraries is about a second of CPU, 15 on an emulated VM).
# Sets $vpn and $master (yes/no).
SERVING_SH = r"""ros2_ok() {
  [ -e /run/ccrp-ros2.ok ] && return 0
  if [ -e /etc/systemd/system/ccrp-graph.service ]; then
    [ -S /run/ccrp-graph/graph.sock ]
    return
  fi
  ( set -a; . /etc/ccrp/ros.env; set +a
    logs=$(mktemp -d) && chown ros "$logs" || exit 1
    ROS_LOG_DIR=$logs HOME=/var/lib/ros /usr/sbin/runuser -u ros -- "/opt/ros/$ROS_DISTRO/bin/python" \
      /usr/local/lib/ccrp/ros2_graph.py check >/dev/null 2>&1
    rc=$?; rm -rf "$logs"; exit $rc ) && touch /run/ccrp-ros2.ok
}
serving() {
  vpn=no master=no
  systemctl is-active --quiet ccrp-openvpn.service && [ -n "$(ss -Hxl src "$MGMT")" ] && vpn=yes
  if [ "$PORT" = ros2 ]; then
    [ $vpn = yes ] && ros2_ok && master=yes
    [ $vpn = yes ] && [ $master = yes ]
    return
  fi
  local body="<?xml version='1.0'?><methodCall><methodName>getPid</methodName><params><param><value><string>/ccrp_fleet_up</string></value></param></params></methodCall>"
  local reply
  reply=$({ printf 'POST / HTTP/1.0\r\nContent-Type: text/xml\r\nContent-Length: %d\r\n\r\n%s' "${#body}" "$body" >&0
            timeout 3 cat; } 2>/dev/null <>"/dev/tcp/127.0.0.1/$PORT" | tr -d '\r\n')
  case $reply in *'<methodResponse><params><param><value><array><data><value><int>1</int>'*) master=yes ;; esac
  [ $vpn = yes ] && [ $master = yes ]
}
"""
# Until the clone serves ($0 management socket, $1 master port).
WAIT_SERVING_SH = SERVING_SH + """MGMT=$0 PORT=$1
until [ -S "$MGMT" ] && serving; do sleep 0.2; done
echo "vpn=$vpn master=$master"
"""
# A running clone in one round trip ($0 management socket, $1 master port, then files): cloud-init's
# result of this boot (/run is a tmpfs), the sha256 of those files it holds, and whether it serves.
PROBE_SH = SERVING_SH + """MGMT=$0 PORT=$1
shift
printf '== result\n'; cat /run/cloud-init/result.json 2>/dev/null
printf '\n== digests\n'; [ $# -eq 0 ] || sha256sum "$@" 2>/dev/null
serving; echo "== serving vpn=$vpn master=$master"
"""


@dataclass
class Probe:
    booted: bool  # cloud-init finished this boot without errors
    digests: dict[str, str]  # path -> sha256 of the probed files the clone holds
    serving: bool  # VPN server up and the master answering


def serving_port(inv: Inventory) -> str:
    """What SERVING_SH checks besides the VPN: the master's port, or `ros2` (no master)."""
    return "ros2" if inv.ros.ros2 else str(inv.ros.master_port)


def probe(provider: Reaches, robot: str, master_port: int | str, files: list[BundleFile]) -> Probe | None:
    """What `fleet up` must know of a running clone, in one command: None when the probe could not
    run (the caller then asks the long way)."""
    try:
        rc, out = provider.transport.exec(robot, ["bash", "-c", PROBE_SH, MGMT_SOCKET, str(master_port),
                                          *(cast(str, f.dest) for f in files)], timeout=20)  # pushed files: each has its dest
    except CcrpError:
        return None
    head, sep, rest = out.partition("== result\n")
    result, sep2, rest = rest.partition("\n== digests\n")
    digests, sep3, tail = rest.rpartition("== serving ")
    if rc != 0 or not (sep and sep2 and sep3):
        return None
    have = {line.split()[1]: line.split()[0] for line in digests.splitlines() if len(line.split()) == 2}
    return Probe(cloud_init_clean(result), have, tail.split() == ["vpn=yes", "master=yes"])


def wait_serving(provider: Reaches, robot: str, master_port: int | str, timeout: float = 60) -> None:
    """Until the VPN server runs and the ROS master answers inside the clone (ROS 2: its
    environment works, see SERVING_SH)."""
    rc, out = provider.transport.exec(robot, ["bash", "-c", WAIT_SERVING_SH, MGMT_SOCKET, str(master_port)], timeout=timeout)
    if rc != 0 or out.split()[-2:] != ["vpn=yes", "master=yes"]:
        detail = json.dumps(health(provider, robot))[:300]  # the long way, for the message only
        waited = timeout * provider.timeout_scale(robot)  # as the transport stretched it
        raise CcrpError(f"clone {clone_host(robot)} is not serving after {waited:.0f} s: {detail}")


def clone_user_data(view: CloneView, provider: Housekeeping, bare: bool) -> str:
    """A cloud clone gets ccrp's login user (render/view.py LOGIN_USER) with the fleet's operator key:
    the SSH transport logs in as it. A Docker clone has no login user; its transport is the Docker API."""
    from ..render import cloudinit
    from ..services.registry import boots

    return cloudinit.user_data(view, boots(), login_keys=provider.login_keys(), install_packages=bare)


def ensure_clone(fleet: Fleet, provider: Provider, writer: StateWriter, robot: str, progress: Progress,
                 deployed: tuple[str, str] | None = None) -> CloneResult:
    """Create or reuse the clone of `robot`, push its secrets, wait until it serves, then bring each
    clone service (services/registry.py) in line, in the registry's order. `deployed`: (digest,
    install space) of the inventory's software as `ccrp deploy` pushed it, which a clone made or
    started now gets before its nodes are brought in line (a clone that was running keeps what it
    runs: `ccrp deploy` changes it, and `deploy --rollback` may have put it back on purpose)."""
    from ..services.registry import SERVICES
    from ..providers import info
    from ..render import bundles
    from ..services.base import ServiceContext
    from ..services.workloads import NO_SOFTWARE

    t0 = time.monotonic()
    state = writer.state
    view = clone_view(fleet, state, robot)
    # up() issued the certificates of every robot in one batch (PkiStore.issue_fleet), except a
    # revoked robot's.
    since = fleet.pki.revoked_since(robot)
    if since is not None:
        with writer.lock:
            return _left_revoked(fleet, provider, writer, robot, fleet.pki.unenrolled(robot, since), progress)
    # A bare snapshot gets the recipe's packages from cloud-init at first boot.
    bare = bool(state.snapshot and state.snapshot.get("bare"))
    user_data = clone_user_data(view, provider, bare)
    info(provider.kind).fit_user_data(user_data)
    for service in SERVICES:  # what the operator's inputs make impossible is refused before a clone exists
        service.check(fleet, view.robot)
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
    port = serving_port(fleet.inventory)
    try:
        secrets = bundles.clone_secrets(view, fleet.pki.credentials(robot))
        keys = [f for f in secrets if f.name != "crl.pem"]
        crl = [f for f in secrets if f.name == "crl.pem"]
        applied = applied_marker(keys)
        # A clone kept runs the software it has (`ccrp deploy` may have changed it since its snapshot).
        runs = (state.snapshot or {}).get("software", NO_SOFTWARE)
        if not record.created and rec.software:
            runs = rec.software
        install = deployed if deployed and record.origin is not Origin.REUSED and runs != deployed[0] else None
        software = install[0] if install else runs
        ctx = ServiceContext(fleet, state, view.robot, writer.live(), software)
        wanted = {s.name: s.files(ctx) for s in SERVICES}
        settings = [f for s in SERVICES if s.settings for f in wanted[s.name]]
        # A service without files has its "absent" marker probed: the clone may still run it.
        probed = [*secrets, applied, *(f for s in SERVICES for f in wanted[s.name] or s.absent())]
        # A clone that was running already: cloud-init's result, the digests of what ccrp put there
        # and whether it serves, in one round trip. Anything not as it should be is then done the
        # long way below, as for a new clone. A clone just created or started boots first.
        seen = probe(provider, robot, port, probed) if record.origin is Origin.REUSED else None
        if seen is None or not seen.booted:
            provider.wait_ready(robot, timeout=1200 if bare else 300)
            seen = probe(provider, robot, port, probed)
        have = seen.digests if seen is not None else remote_digests(provider, robot, probed)
        # Settings before keys: a started clone's autostop agent counts idle time from when OpenVPN
        # serves, so it must have the current setting by then (an old, shorter one powered the clone
        # off while ccrp was still waiting for its master).
        changed = [f for f in settings if not same(have, [f])]
        if changed:
            provider.transport.push_files(robot, changed, restart=[])  # their agents re-read their files
        pushed = False
        if not same(have, [*keys, applied]):
            prepare_secrets_dir(provider, robot)
            provider.transport.push_files(robot, secrets, restart=keyed_units(fleet.inventory))
            provider.transport.push_files(robot, [applied])  # last: until it is there, the next run pushes again
            pushed = True
        elif not same(have, crl):
            # Only the CRL changed (another robot was revoked): OpenVPN re-reads it, the robot's
            # live session stays.
            provider.transport.push_files(robot, crl, restart=[])
        if pushed or seen is None or not seen.serving:
            wait_serving(provider, robot, port)
        if install:  # before its nodes are brought in line: they restart on it (ccrp deploy's install space)
            install_space.install(provider, robot, *install)
            progress(f"[{robot}] workspace {runs} -> {software}: the deployed software")
        # What a service started must stay up (the robot's nodes: deploy's health check, one window
        # for them all): a node that crash-loops is not "started". A clone just created or started
        # has booted, and its enabled units with it.
        booted, failing = record.origin is not Origin.REUSED, []
        for service in SERVICES:
            started = service.apply(provider, robot, wanted[service.name], have, pushed)
            why = service.verify(provider, robot, wanted[service.name], started, booted)
            if why is not None:
                failing.append(why)
            elif started:
                progress(f"[{robot}] {service.name} started: {', '.join(started)}")
        writer.relay_current[robot] = "".join(f.content for s in SERVICES if s.reshared for f in wanted[s.name])
    except BaseException:
        writer.update(robot, phase="failed", provider_id=record.provider_id)
        if record.created:
            provider.terminate(robot)  # roll back only what this attempt created
        raise
    endpoint = gateway.endpoint(fleet, state, robot) if gateway.in_use(fleet) else (record.endpoint or record.public_ip)
    before = rec.public_endpoint
    if before and endpoint != before:  # a new address, or the fleet's entry changed: the robot's bundle dials the old
        progress(f"[{robot}] its robot now dials {endpoint} (was {before}): give it its new bundle, "
                 f"`ccrp robot bundle {robot}`")
    writer.update(
        robot, phase="ready", provider_id=record.provider_id, public_endpoint=endpoint,
        # The snapshot's id (one image may carry several names): a reused clone keeps its own.
        image=((state.snapshot or {}).get("id") or image) if record.created else rec.image,
        software=software if install or record.created else rec.software,
        packages=(state.snapshot or {}).get("packages") if record.created else rec.packages,
        addresses={"public": record.public_ip or "", "common": str(view.addr.common_ip),
                   "vpn": str(view.addr.clone_vpn_ip), "robot_vpn": str(view.addr.robot_vpn_ip)},
    )
    if failing:
        # The clone serves and is recorded (its nodes' logs can be read); the command fails for it.
        raise CcrpError("; ".join(failing))
    took = time.monotonic() - t0
    progress(f"[{robot}] clone {view.addr.clone_host} ready in {took:.1f}s ({endpoint})")
    return CloneResult(robot, "created" if record.created else "reused", endpoint or "", took, record.origin)


def _left_revoked(fleet: Fleet, provider: Lifecycle, writer: StateWriter, robot: str, revoked: CcrpError,
                  progress: Progress) -> CloneResult:
    """A revoked robot stays unenrolled: no certificate, no clone created or configured. A clone
    of it that runs gets the current CRL and the kill again, in case `vpn revoke` could not reach
    it: a failed TLS renegotiation alone does not end a session (docs/security.md)."""
    from ..render.bundles import crl_file

    writer.state.robots[robot].phase = "revoked"
    writer.fleet.store.save_state(writer.state)  # the caller holds writer.lock
    rec = provider.query().get(robot)
    if rec is not None and rec.state is CloneState.RUNNING:
        provider.transport.push_files(robot, [crl_file(fleet.pki.crl_path.read_text())], restart=[])
        kill_session(provider, robot)
    progress(f"[{robot}] {revoked.message}")
    return CloneResult(robot, "revoked", revoked.message + f" ({revoked.hint})")


def push_relay_config(fleet: Fleet, provider: Reaches, state: FleetState, robot: str, known: str | None = None) -> bool:
    """Give robot's clone the current files of the services that name its partners (relay.json, and
    knowledge.json where it shares a dataset); the agents pick them up without a restart. `known` is
    what this run already found on (or pushed to) the clone: when it is the same, the clone is not
    asked again. Returns True when a file changed."""
    from ..services.registry import SERVICES
    from ..services.base import ServiceContext

    ctx = ServiceContext(fleet, state, fleet.robot(state, robot))
    files = [f for s in SERVICES if s.reshared for f in s.files(ctx)]
    if "".join(f.content for f in files) == known or files_current(provider, robot, files):
        return False
    provider.transport.push_files(robot, files, restart=[])
    return True


def delete_clone(fleet: Fleet, provider: Lifecycle, writer: StateWriter, robot: str, forget: bool) -> CloneResult:
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
