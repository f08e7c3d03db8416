"""Docker provider: clones are systemd containers on <fleet>-public and <fleet>-common, booted
by cloud-init from a NoCloud seed with the same user-data a cloud VM gets. Secrets go through the
Docker API into a per-clone volume, never into user-data, labels, environment or image layers.

This class is the containers' lifecycle, in the backends' one shape: its client is client.py's
DockerHost (the engine, which simulated robots and libvirt's fleets use alone too), taken by the
fleet's networks (network.py), its snapshot images (images.py) and what the fleet owns (owned.py)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import cast

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...models.layout import AUTOSTOP_NOTE, VPN_DIR
from ..base import (
    LABEL_ROBOT, CloneRecord, CloneSpec, CloneState, Composed, Finding, ImageOutcome, Origin,
    Quota, RobotAttachment, SnapshotRecord,
    autostop_note, owner_labels, wait_cloud_init,
)
from . import INFO, images, network, owned, snapshot_images
from .archive import tar_files
from .client import DockerHost, EngineTransport
from .settings import DockerSettings

SEED_DIR = "var/lib/cloud/seed/nocloud"
# What a systemd container (a clone, a simulated robot) gets beyond Docker's defaults: NET_ADMIN for
# the tunnel and the firewall, SYS_ADMIN for systemd's per-unit mount namespaces. Docker's default
# seccomp profile stays on (it allows mount/unshare to a SYS_ADMIN container).
CLONE_CAPS = ["NET_ADMIN", "SYS_ADMIN"]
CLONE_SECURITY_OPT = ["no-new-privileges"]
# Docker's container states in ccrp's words.
STATES = {"created": CloneState.PENDING, "restarting": CloneState.PENDING, "running": CloneState.RUNNING,
          "paused": CloneState.STOPPED, "exited": CloneState.STOPPED, "removing": CloneState.DELETING,
          "dead": CloneState.ERROR}


class DockerProvider(Composed):
    kind = "docker"
    abilities = INFO.abilities
    images, owned = images, owned  # snapshots and owned resources: base.Composed hands them the client
    max_parallel = 8  # clones at once in `fleet up`: containers boot on this host's CPUs

    def __init__(self, inv: Inventory, workdir: Path | None = None) -> None:
        self.inv, self.fleet = inv, inv.fleet
        # workdir: the fleet's state directory (providers.get_provider: the store's root).
        self.client = DockerHost(inv.fleet, workdir)
        # The engine reaches into its containers itself (exec_run, archive uploads): no login or
        # session to keep, so one transport for the provider's life.
        self._transport = EngineTransport(self.client)

    @property
    def transport(self) -> EngineTransport:
        return self._transport

    # -- the fleet's networks (network.py) ---------------------------------------------------------
    def bootstrap(self) -> None:
        network.bootstrap(self.client, self.inv)

    # -- clones -------------------------------------------------------------------------------
    def _record(self, c, origin: Origin | None = None) -> CloneRecord:
        nets = c.attrs.get("NetworkSettings", {}).get("Networks", {})
        return CloneRecord(
            robot=c.labels.get(LABEL_ROBOT, ""),
            provider_id=c.id[:12],
            state=CloneState.of(c.status, STATES),
            status=c.status,
            public_ip=(nets.get(self.client.public_net) or {}).get("IPAddress") or None,
            common_ip=(nets.get(self.client.common_net) or {}).get("IPAddress") or None,
            origin=origin,
        )

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Create the clone container (or reuse the one carrying its labels) and boot it."""
        existing = self.client.container(spec.robot)
        if existing is not None and existing.attrs.get("State", {}).get("StartedAt", "").startswith("0001-"):
            # Never started: an interrupted attempt created it and died before it joined the common
            # network and got its NoCloud seed (both happen before the first start). Booting it now
            # would run cloud-init without user-data, so replace it; nothing ever ran in it.
            self._remove(existing, None)
            existing = None
        if existing is not None:
            if existing.status == "running":
                return self._record(existing, Origin.REUSED)
            existing.start()
            existing.reload()
            return self._record(existing, Origin.RESUMED)
        images.ensure_image(self.client, spec.image)
        volume = self.client.volume_name(spec.robot)
        labels = owner_labels(self.fleet, "clone", spec.robot)
        self.client.engine.volumes.create(volume, labels=owner_labels(self.fleet, "secrets", spec.robot))
        ports = {}
        if getattr(self.inv.provider, "publish_vpn_ports", False):
            ports = {f"{self.inv.vpn.port}/{self.inv.vpn.proto}": None}  # a free host port
        c = self.client.engine.containers.create(
            spec.image,
            name=self.client.container_name(spec.robot),
            hostname=spec.hostname,
            labels=labels,
            detach=True,
            network=self.client.public_net,
            # systemd as PID 1, like a VM: its cgroups and /run on tmpfs. SYS_ADMIN is what lets systemd
            # give units their mount namespaces (ProtectSystem, PrivateTmp): without it they run with
            # no sandbox and no error. Docker's default seccomp profile suffices; no-new-privileges
            # makes every setuid binary inert. Measured: docs/security.md "Privileges of Docker clones".
            cap_add=CLONE_CAPS,
            devices=["/dev/net/tun:/dev/net/tun:rwm"],
            tmpfs={"/run": "", "/run/lock": "", "/tmp": ""},
            volumes={"/sys/fs/cgroup": {"bind": "/sys/fs/cgroup", "mode": "ro"}, volume: {"bind": VPN_DIR, "mode": "rw"}},
            security_opt=CLONE_SECURITY_OPT,
            stop_signal="SIGRTMIN+3",
            ports=ports,
        )
        try:
            self.client.engine.networks.get(self.client.common_net).connect(c, ipv4_address=spec.common_ip)
            meta = f"instance-id: {spec.instance_id}\nlocal-hostname: {spec.hostname}\n"
            seed = tar_files(
                [(f"{SEED_DIR}/meta-data", meta.encode(), 0o600), (f"{SEED_DIR}/user-data", spec.user_data.encode(), 0o600)],
                make_dirs=True,
            )
            c.put_archive("/", seed)
            c.start()
            c.reload()
        except BaseException as exc:
            # Roll back only what this call created.
            self._remove(c, volume)
            if isinstance(exc, self.client.APIError):
                raise CcrpError(f"clone {spec.hostname}: {exc.explanation or exc}; rolled back its container and volume") from exc
            raise
        return self._record(c, Origin.CREATED)

    def login_keys(self) -> None:
        return None  # the Docker API is the transport: no login user in the clone

    def resolve_image(self, image: str) -> str:
        return image

    def check_credentials(self) -> str:
        version = self.client.engine.version()  # the engine answering is the credential
        return f"Docker {version.get('Version', '?')} (API {version.get('ApiVersion', '?')})"

    def quotas(self, robots=()) -> list[Quota]:
        # No quota to check before growth: this host's CPUs and memory are the limit (`fleet
        # scale` in docs/benchmarks.md), and the engine answers at once when one runs out.
        return []

    def timeout_scale(self, robot: str) -> int:
        return 1

    def close(self) -> None:
        self.client.engine.close()

    def wait_ready(self, robot: str, timeout: float = 300) -> None:
        """Wait for cloud-init to finish inside the clone; fail with its own error detail."""
        wait_cloud_init(robot, lambda argv: self.client.exec(robot, argv, timeout=timeout), timeout)

    def query(self) -> dict[str, CloneRecord]:
        return {
            r.robot: r for r in (self._record(c) for c in self.client.engine.containers.list(all=True, ignore_removed=True, filters=self.client.filters("clone")))
        }

    def _remove(self, container, volume: str | None) -> None:
        try:
            container.remove(force=True, v=True)
        except self.client.NotFound:
            pass
        if volume:
            try:
                self.client.engine.volumes.get(volume).remove(force=True)
            except self.client.NotFound:
                pass

    def stop_instance(self, robot: str) -> bool:
        c = self.client.container(robot)
        if c is None or c.status != "running":
            return False
        c.stop(timeout=60)  # SIGRTMIN+3 (the container's stop signal): systemd shuts the clone down
        return True

    def terminate(self, robot: str) -> bool:
        c = self.client.container(robot)
        if c is not None:
            self._remove(c, self.client.volume_name(robot))
            return True
        for v in self.client.engine.volumes.list(filters=self.client.filters("secrets", robot)):
            v.remove(force=True)
        return False

    # -- snapshots: images of this engine (images.py) --------------------------------------------
    def build_snapshot(self, repo: str, distro: str, plat, agents: tuple[str, ...], software, digest: str, bare: bool,
                       progress) -> SnapshotRecord:
        return images.build_snapshot(self.client, repo, distro, cast(DockerSettings, self.inv.provider).base_image,
                                     plat, agents, software, digest, bare, progress)

    def snapshot_labels(self, robot: str | None = None) -> dict[str, str]:
        return images.snapshot_labels(self.client, robot)

    def snapshot_record(self, image) -> SnapshotRecord:
        return images.snapshot_record(image)

    # -- snapshot images of other states (Ability.HOST_IMAGES, snapshot_images.py) ----------------
    def sweep_images(self, dry_run: bool, unlabelled: bool, progress=lambda msg: None) -> list[ImageOutcome]:
        return snapshot_images.sweep(self.client.engine, self.fleet, self.client.state_dir, dry_run, unlabelled, progress)

    def images_finding(self) -> Finding:
        return snapshot_images.finding(self.client.engine, self.fleet, self.client.state_dir)

    def stop_note(self, robot: str) -> str | None:
        """From the stopped container's disk: a Docker clone has no console that outlives it."""
        import io
        import tarfile

        c = self.client.container(robot)
        if c is None:
            return None
        try:
            stream, _ = c.get_archive(AUTOSTOP_NOTE)
            with tarfile.open(fileobj=io.BytesIO(b"".join(stream))) as tar:
                member = tar.extractfile(tar.getmembers()[0])
                return autostop_note(member.read().decode(errors="replace")) if member else None
        except (self.client.NotFound, tarfile.TarError, IndexError):
            return None

    # -- simulated robots (Ability.ROBOT_ATTACH: their containers are robots.RobotContainers) -------
    def attach_robot(self, robot: str, index: int) -> RobotAttachment:
        # On <fleet>-public only, as a robot on the clones' LAN; it runs the fleet's snapshot, a
        # Docker image of this engine already (the simulated robots' own image is not built).
        return RobotAttachment(network=self.client.public_net, clone_image=True)

    def detach_robot(self, robot: str) -> None:
        pass  # nothing outlives the robot's container: its network is the fleet's


def now_tag() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d%H%M%S")
