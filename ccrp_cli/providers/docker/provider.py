"""Docker provider: clones are systemd containers on <fleet>-public and <fleet>-common, booted
by cloud-init from a NoCloud seed with the same user-data a cloud VM gets. Secrets go through the
Docker API into a per-clone volume, never into user-data, labels, environment or image layers."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...models.layout import AUTOSTOP_NOTE, VPN_DIR
from ...store import FleetStore, ensure_state_id, read_state_id
from ..base import (
    LABEL_FLEET, LABEL_ROBOT, LABEL_ROLE, CloneRecord, CloneSpec, CloneState, Finding, ImageOutcome, Origin,
    OwnedResource, Quota, RobotAttachment, Role, SnapshotRecord,
    autostop_note, with_roles, owner_labels, wait_cloud_init,
)
from . import INFO, snapshot_images
from .archive import tar_files
from .host import DockerHost, EngineTransport

SEED_DIR = "var/lib/cloud/seed/nocloud"
# What a systemd container (a clone, a simulated robot) gets beyond Docker's defaults: NET_ADMIN for
# the tunnel and the firewall, SYS_ADMIN for systemd's per-unit mount namespaces. Docker's default
# seccomp profile stays on (it allows mount/unshare to a SYS_ADMIN container).
# What each kind is to the fleet (`ccrp gc`); volumes belong to a robot.
ROLES = {"container": Role.CLONE, "robot_sim": Role.ROBOT_SIDE, "image": Role.IMAGE, "network": Role.BOOTSTRAP}
CLONE_CAPS = ["NET_ADMIN", "SYS_ADMIN"]
CLONE_SECURITY_OPT = ["no-new-privileges"]
# Docker's container states in ccrp's words.
STATES = {"created": CloneState.PENDING, "restarting": CloneState.PENDING, "running": CloneState.RUNNING,
          "paused": CloneState.STOPPED, "exited": CloneState.STOPPED, "removing": CloneState.DELETING,
          "dead": CloneState.ERROR}


class DockerProvider(DockerHost):
    kind = "docker"
    abilities = INFO.abilities
    max_parallel = 8  # clones at once in `fleet up`: containers boot on this host's CPUs

    def __init__(self, inv: Inventory, workdir: Path | None = None) -> None:
        super().__init__(inv.fleet)
        self.inv = inv
        # The fleet's state directory (providers.get_provider: the store's root): its id labels
        # the snapshot images, so `ccrp gc` can tell whose they are.
        self.state_dir = workdir or FleetStore(inv.fleet).root
        # The engine reaches into its containers itself (exec_run, archive uploads): no login or
        # session to keep, so one transport for the provider's life.
        self._transport = EngineTransport(self)

    @property
    def transport(self) -> EngineTransport:
        return self._transport

    # -- networks -----------------------------------------------------------------------------
    def bootstrap(self) -> None:
        """Create (or reuse) the fleet's public and common networks."""
        from docker.types import IPAMConfig, IPAMPool

        provider = self.inv.provider
        for name, cidr, internal in (
            (self.public_net, provider.public_cidr, False),  # type: ignore[union-attr]
            (self.common_net, self.inv.common.cidr, True),
        ):
            existing = self.client.networks.list(names=[name])
            existing = [n for n in existing if n.name == name]
            if existing:
                if existing[0].attrs.get("Labels", {}).get(LABEL_FLEET) != self.fleet:
                    raise CcrpError(f"Docker network {name} exists and is not ccrp's", hint="remove or rename it")
                continue
            try:
                self.client.networks.create(
                    name, driver="bridge", internal=internal, labels=owner_labels(self.fleet, "network"),
                    ipam=IPAMConfig(pool_configs=[IPAMPool(subnet=str(cidr))]),
                )
            except self._APIError as exc:
                raise CcrpError(
                    f"cannot create Docker network {name} ({cidr}): {exc.explanation}",
                    hint="another network uses that subnet: change provider.public_cidr or common.cidr",
                ) from None

    # -- clones -------------------------------------------------------------------------------
    def _record(self, c, origin: Origin | None = None) -> CloneRecord:
        nets = c.attrs.get("NetworkSettings", {}).get("Networks", {})
        return CloneRecord(
            robot=c.labels.get(LABEL_ROBOT, ""),
            provider_id=c.id[:12],
            state=CloneState.of(c.status, STATES),
            status=c.status,
            public_ip=(nets.get(self.public_net) or {}).get("IPAddress") or None,
            common_ip=(nets.get(self.common_net) or {}).get("IPAddress") or None,
            origin=origin,
        )

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Create the clone container (or reuse the one carrying its labels) and boot it."""
        existing = self._container(spec.robot)
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
        self._ensure_image(spec.image)
        volume = self.volume_name(spec.robot)
        labels = owner_labels(self.fleet, "clone", spec.robot)
        self.client.volumes.create(volume, labels=owner_labels(self.fleet, "secrets", spec.robot))
        ports = {}
        if getattr(self.inv.provider, "publish_vpn_ports", False):
            ports = {f"{self.inv.vpn.port}/{self.inv.vpn.proto}": None}  # a free host port
        c = self.client.containers.create(
            spec.image,
            name=self.container_name(spec.robot),
            hostname=spec.hostname,
            labels=labels,
            detach=True,
            network=self.public_net,
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
            self.client.networks.get(self.common_net).connect(c, ipv4_address=spec.common_ip)
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
            if isinstance(exc, self._APIError):
                raise CcrpError(f"clone {spec.hostname}: {exc.explanation or exc}; rolled back its container and volume") from exc
            raise
        return self._record(c, Origin.CREATED)

    def login_keys(self) -> None:
        return None  # the Docker API is the transport: no login user in the clone

    def resolve_image(self, image: str) -> str:
        return image

    def check_credentials(self) -> str:
        version = self.client.version()  # the engine answering is the credential
        return f"Docker {version.get('Version', '?')} (API {version.get('ApiVersion', '?')})"

    def quotas(self, robots=()) -> list[Quota]:
        # No quota to check before growth: this host's CPUs and memory are the limit (`fleet
        # scale` in docs/benchmarks.md), and the engine answers at once when one runs out.
        return []

    def timeout_scale(self, robot: str) -> int:
        return 1

    def close(self) -> None:
        self.client.close()

    def has_image(self, image: str) -> bool:
        try:
            self.client.images.get(image)
            return True
        except self._NotFound:
            return False

    def _ensure_image(self, image: str) -> None:
        try:
            self.client.images.get(image)
        except self._NotFound:
            raise CcrpError(f"snapshot image {image} not found", hint="run `ccrp snapshot build -i INVENTORY`") from None

    def wait_ready(self, robot: str, timeout: float = 300) -> None:
        """Wait for cloud-init to finish inside the clone; fail with its own error detail."""
        wait_cloud_init(robot, lambda argv: self.exec(robot, argv, timeout=timeout), timeout)

    def query(self) -> dict[str, CloneRecord]:
        return {
            r.robot: r for r in (self._record(c) for c in self.client.containers.list(all=True, ignore_removed=True, filters=self._filters("clone")))
        }

    def _remove(self, container, volume: str | None) -> None:
        try:
            container.remove(force=True, v=True)
        except self._NotFound:
            pass
        if volume:
            try:
                self.client.volumes.get(volume).remove(force=True)
            except self._NotFound:
                pass

    def stop_instance(self, robot: str) -> bool:
        c = self._container(robot)
        if c is None or c.status != "running":
            return False
        c.stop(timeout=60)  # SIGRTMIN+3 (the container's stop signal): systemd shuts the clone down
        return True

    def terminate(self, robot: str) -> bool:
        c = self._container(robot)
        if c is not None:
            self._remove(c, self.volume_name(robot))
            return True
        for v in self.client.volumes.list(filters=self._filters("secrets", robot)):
            v.remove(force=True)
        return False

    # -- snapshots ----------------------------------------------------------------------------
    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        c = self._running(robot)
        # The secrets volume is not part of a commit: the snapshot carries no key.
        repo, _, tag = name.rpartition(":")
        # Labels through the config, not a LABEL line: the state directory's path is taken as it
        # is (spaces, quotes, `$`), and these win over the clone's own labels the image inherits.
        image = c.commit(repository=repo, tag=tag, conf={"Labels": self.snapshot_labels(robot)})
        return self.snapshot_record(image)

    def build_snapshot(self, repo: str, distro: str, plat, agents: tuple[str, ...], software, digest: str, bare: bool,
                       progress) -> SnapshotRecord:
        """Ability.LOCAL_BUILD: the clone image built on this engine (images.build_snapshot_image)."""
        from . import images

        tag = images.build_snapshot_image(self.client, repo, self.fleet, distro, self.inv.provider.base_image,  # type: ignore[union-attr]
                                          plat, agents, software, bare, self.snapshot_labels() | {"ccrp-software": digest},
                                          progress)
        return self.snapshot_record(self.client.images.get(tag))

    def snapshot_labels(self, robot: str | None = None) -> dict[str, str]:
        """Owner labels of a snapshot image, with the state it belongs to (`ccrp gc` finds the
        images of deleted state directories by them)."""
        from .snapshot_images import state_labels

        return owner_labels(self.fleet, "snapshot", robot) | state_labels(self.state_dir, ensure_state_id(self.state_dir))

    def snapshot_record(self, image) -> SnapshotRecord:
        return SnapshotRecord(
            id=image.id.removeprefix("sha256:")[:12],
            name=(image.tags or ["<untagged>"])[0],
            created=image.attrs.get("Created", "")[:19],
            source=image.labels.get(LABEL_ROBOT) or "build",
            size_mb=round(image.attrs.get("Size", 0) / 1e6, 1),
        )

    def list_snapshots(self) -> list[SnapshotRecord]:
        """This state's snapshots, and the fleet's from before images were labelled with their
        state: a fleet of the same name in another CCRP_HOME has its own (retention and gc of
        this one must not touch them)."""
        from .snapshot_images import LABEL_STATE_ID

        mine = read_state_id(self.state_dir)
        images = [i for i in self.client.images.list(filters=self._filters("snapshot"))
                  if i.labels.get(LABEL_STATE_ID) in (None, mine)]
        return sorted((self.snapshot_record(i) for i in images), key=lambda s: s.created)

    # -- snapshot images of other states (Ability.HOST_IMAGES, snapshot_images.py) ----------------
    def sweep_images(self, dry_run: bool, unlabelled: bool, progress=lambda msg: None) -> list[ImageOutcome]:
        return snapshot_images.sweep(self.client, self.fleet, self.state_dir, dry_run, unlabelled, progress)

    def images_finding(self) -> Finding:
        return snapshot_images.finding(self.client, self.fleet, self.state_dir)

    def delete_snapshot(self, snapshot_id: str) -> None:
        try:
            image = self.client.images.get(snapshot_id)
        except self._NotFound:
            raise CcrpError(f"snapshot {snapshot_id} not found", hint="ccrp snapshot list") from None
        if image.labels.get(LABEL_FLEET) != self.fleet:
            raise CcrpError(f"image {snapshot_id} is not a snapshot of fleet {self.fleet!r}")
        self.client.images.remove(image.id, force=True)

    def stop_note(self, robot: str) -> str | None:
        """From the stopped container's disk: a Docker clone has no console that outlives it."""
        import io
        import tarfile

        c = self._container(robot)
        if c is None:
            return None
        try:
            stream, _ = c.get_archive(AUTOSTOP_NOTE)
            with tarfile.open(fileobj=io.BytesIO(b"".join(stream))) as tar:
                member = tar.extractfile(tar.getmembers()[0])
                return autostop_note(member.read().decode(errors="replace")) if member else None
        except (self._NotFound, tarfile.TarError, IndexError):
            return None

    # -- simulated robots (Ability.ROBOT_ATTACH: their containers are robots.RobotContainers) -------
    def attach_robot(self, robot: str, index: int) -> RobotAttachment:
        # On <fleet>-public only, as a robot on the clones' LAN; it runs the fleet's snapshot, a
        # Docker image of this engine already (the simulated robots' own image is not built).
        return RobotAttachment(network=self.public_net, clone_image=True)

    def detach_robot(self, robot: str) -> None:
        pass  # nothing outlives the robot's container: its network is the fleet's

    # -- whole fleet ----------------------------------------------------------------------------
    def teardown(self) -> list[str]:
        """Remove every container, volume and network carrying the fleet's labels."""
        removed = []
        found = self.client.containers.list(all=True, ignore_removed=True, filters={"label": [f"{LABEL_FLEET}={self.fleet}"]})
        # A simulated power device first: it holds its robot's power-line volume, which goes with the robot.
        for c in sorted(found, key=lambda c: c.labels.get(LABEL_ROLE) != "power-sim"):
            c.remove(force=True, v=True)
            removed.append(f"container {c.name}")
        for v in self.client.volumes.list(filters={"label": [f"{LABEL_FLEET}={self.fleet}"]}):
            v.remove(force=True)
            removed.append(f"volume {v.name}")
        for n in self.client.networks.list(filters={"label": [f"{LABEL_FLEET}={self.fleet}"]}):
            n.remove()
            removed.append(f"network {n.name}")
        return removed

    # -- everything owned (gc) -------------------------------------------------------------------
    def list_owned(self) -> list[OwnedResource]:
        label = {"label": [f"{LABEL_FLEET}={self.fleet}"]}
        owned = [
            OwnedResource(kind="container" if c.labels.get(LABEL_ROLE) == "clone" else "robot_sim", id=c.id[:12],
                          name=c.name, robot=c.labels.get(LABEL_ROBOT))
            for c in self.client.containers.list(all=True, ignore_removed=True, filters=label)
        ]
        owned += [OwnedResource(kind="volume", id=v.name, name=v.name, robot=(v.attrs.get("Labels") or {}).get(LABEL_ROBOT))
                  for v in self.client.volumes.list(filters=label)]
        owned += [OwnedResource(kind="network", id=n.name, name=n.name) for n in self.client.networks.list(filters=label)]
        owned += [OwnedResource(kind="image", id=s.id, name=s.name, robot=None if s.source == "build" else s.source)
                  for s in self.list_snapshots()]
        # `ccrp deploy`'s build of the workspace (deploy.py): cache only, no state records it.
        owned += [OwnedResource(kind="image", id=i.id.removeprefix("sha256:")[:12], name=(i.tags or ["<untagged>"])[0])
                  for i in self.client.images.list(filters=self._filters("deploy"))]
        return with_roles(owned, ROLES)

    def delete_owned(self, resource: OwnedResource) -> None:
        getter = {"container": self.client.containers, "robot_sim": self.client.containers, "volume": self.client.volumes,
                  "network": self.client.networks, "image": self.client.images}[resource.kind]
        try:
            obj = getter.get(resource.id)
        except self._NotFound:
            raise CcrpError(f"{resource.kind} {resource.id} is gone") from None
        labels = obj.labels if resource.kind in ("container", "robot_sim", "image") else obj.attrs.get("Labels") or {}
        if labels.get(LABEL_FLEET) != self.fleet:  # checked again: never remove what is not ours
            raise CcrpError(f"{resource.kind} {resource.id} is not owned by fleet {self.fleet!r}")
        if resource.kind == "image":
            self.client.images.remove(obj.id, force=True)
        elif resource.kind == "network":
            obj.remove()
        else:
            obj.remove(force=True, **({"v": True} if resource.kind != "volume" else {}))

    def leftovers(self) -> list[str]:
        label = {"label": [f"{LABEL_FLEET}={self.fleet}"]}
        return (
            [f"container {c.name}" for c in self.client.containers.list(all=True, ignore_removed=True, filters=label)]
            + [f"volume {v.name}" for v in self.client.volumes.list(filters=label)]
            + [f"network {n.name}" for n in self.client.networks.list(filters=label)]
        )


def now_tag() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d%H%M%S")
