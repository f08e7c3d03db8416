"""The memory backend's provider (tests only): the provider protocol (ccrp_cli/providers/base.py)
over the memory cloud's API (cloud.py), every call through retry.call as a cloud SDK's is."""

from __future__ import annotations

from pathlib import Path

from ccrp_cli import retry
from ccrp_cli.errors import CcrpError
from ccrp_cli.models.inventory import Inventory
from ccrp_cli.providers.base import (
    LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, CloneRecord, CloneSpec, CloneState, Origin,
    OwnedResource, Quota, Role, SnapshotRecord, autostop_note, owner_labels, with_roles,
)

from . import INFO, cloud
from .cloud import Resource, Throttled

STATES = {"pending": CloneState.PENDING, "running": CloneState.RUNNING, "stopped": CloneState.STOPPED}
# What teardown removes, in order: an instance before the address it holds, the network last.
TEARDOWN = ("instance", "address", "firewall", "network")
# What each kind is to the fleet (`ccrp gc`); an address belongs to a robot.
ROLES = {"instance": Role.CLONE, "image": Role.IMAGE, "firewall": Role.BOOTSTRAP, "network": Role.BOOTSTRAP}


def _classify(exc: BaseException) -> retry.ErrorClass:
    return retry.ErrorClass.RETRYABLE if isinstance(exc, Throttled) else retry.ErrorClass.FATAL


class MemoryTransport:
    """base.Transport on the memory cloud: commands and files go to the robot's running instance
    (a clone, or `snapshot bake`'s builder), found by its labels."""

    def __init__(self, provider: MemoryProvider) -> None:
        self.provider = provider

    def instance(self, robot: str) -> Resource:
        p = self.provider
        found = [r for r in p._owned("instance", robot) if r.data["state"] == "running"]
        if not found:
            raise CcrpError(f"clone of robot {robot!r} is not running", hint=f"ccrp clone create --robot {robot}")
        return found[0]

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        return self.provider.api("run command", self.provider.cloud.run, self.instance(robot).id, list(argv))

    def push_files(self, robot: str, files, restart=()) -> None:
        entries = [(f.dest, f.content, f.mode, f.group) for f in files]
        self.provider.api("write files", self.provider.cloud.write, self.instance(robot).id, entries, list(restart))


class MemoryProvider:
    kind = INFO.kind
    abilities = INFO.abilities
    max_parallel = 8
    backoff = retry.Backoff()

    def __init__(self, inv: Inventory, workdir: Path | None = None) -> None:
        self.inv, self.fleet = inv, inv.fleet
        self.cloud = cloud.CLOUD
        self.transport = MemoryTransport(self)

    def api(self, what: str, fn, *args, **kwargs):
        return retry.call(fn, *args, classify=_classify, what=what, backoff=self.backoff, **kwargs)

    def _owned(self, kind: str | None = None, robot: str | None = None, role: str | None = None) -> list[Resource]:
        labels = {LABEL_MANAGED: "true", LABEL_FLEET: self.fleet}
        labels |= ({LABEL_ROBOT: robot} if robot else {}) | ({LABEL_ROLE: role} if role else {})
        return self.api(f"list {kind or 'resources'}", self.cloud.describe, kind, labels)

    def _record(self, inst: Resource, origin: Origin | None = None) -> CloneRecord:
        return CloneRecord(robot=inst.labels[LABEL_ROBOT], provider_id=inst.id,
                           state=CloneState.of(inst.data["state"], STATES), status=inst.data["state"],
                           public_ip=inst.data.get("public_ip"), common_ip=inst.data["common_ip"], origin=origin)

    # -- lifecycle ------------------------------------------------------------------------------
    def bootstrap(self) -> None:
        """The fleet's network and firewall: the VPN from anywhere, everything between clones on the
        common network. No login port: the transport is the cloud's own API, as Docker's is."""
        if not self._owned("network"):
            self.api("create network", self.cloud.create, "network", f"{self.fleet}-net",
                     owner_labels(self.fleet, "network"), cidr=str(self.inv.common.cidr))
        if not self._owned("firewall"):
            rules = [(self.inv.vpn.proto, self.inv.vpn.port, "0.0.0.0/0"), ("all", -1, str(self.inv.common.cidr))]
            self.api("create firewall", self.cloud.create, "firewall", f"{self.fleet}-fw",
                     owner_labels(self.fleet, "firewall"), rules=rules)

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Create the robot's instance and its public address, or start or reuse the one it has.
        A create that fails after the instance exists deletes what this call made."""
        payload, gzipped = INFO.fit_user_data(spec.user_data)
        existing = self._owned("instance", spec.robot, spec.role)
        if existing:
            inst = existing[0]
            if inst.data["state"] == "running":
                return self._record(inst, Origin.REUSED)
            self.api("start instance", self.cloud.set_state, inst.id, "running")
            return self._record(self.api("get instance", self.cloud.get, inst.id), Origin.RESUMED)
        if not self.has_image(spec.image):
            raise CcrpError(f"image {spec.image} not found in the memory cloud")
        labels = owner_labels(self.fleet, spec.role, spec.robot)
        inst = self.api("create instance", self.cloud.create, "instance", spec.hostname, labels, state="pending",
                        user_data=payload, gzipped=gzipped, image=spec.image, common_ip=spec.common_ip,
                        public_ip=None, fs={}, console=[], restarted=[])
        made = [inst]
        try:
            self.api("start instance", self.cloud.set_state, inst.id, "running")
            address = self.api("allocate address", self.cloud.create, "address", f"{spec.hostname}-ip", labels)
            made.append(address)
            self.api("associate address", self.cloud.associate, address.id, inst.id)
        except BaseException as exc:
            for res in reversed(made):
                self.api(f"delete {res.kind}", self.cloud.delete, res.id)
            raise CcrpError(f"clone {spec.hostname}: {exc}; rolled back its instance and address") from exc
        return self._record(self.api("get instance", self.cloud.get, inst.id), Origin.CREATED)

    def timeout_scale(self, robot: str) -> int:
        return 1

    def wait_ready(self, robot: str, timeout: float = 60) -> None:
        """Until the robot's instance runs: nothing boots in it, so that is all there is to wait for."""
        def running() -> tuple[bool, str]:
            rec = self.query().get(robot)
            return rec is not None and rec.state is CloneState.RUNNING, rec.status if rec else "gone"

        try:
            retry.poll(running, timeout=timeout, interval=0.1)
        except retry.PollTimeout as late:
            raise CcrpError(f"clone of {robot} is {late.last} after {timeout:.0f} s") from None

    def query(self) -> dict[str, CloneRecord]:
        return {r.labels[LABEL_ROBOT]: self._record(r) for r in self._owned("instance", role="clone")}

    def terminate(self, robot: str) -> bool:
        """The robot's instance (a clone, or the builder) and its address."""
        found = self._owned("instance", robot)
        for res in found + self._owned("address", robot):
            self.api(f"delete {res.kind}", self.cloud.delete, res.id)
        return bool(found)

    def stop_instance(self, robot: str) -> bool:
        found = [r for r in self._owned("instance", robot, "clone") if r.data["state"] == "running"]
        for inst in found:
            self.api("stop instance", self.cloud.set_state, inst.id, "stopped")
        return bool(found)

    def teardown(self) -> list[str]:
        """Everything owned but the snapshots (they outlive the fleet's clones)."""
        doomed = sorted((r for r in self._owned() if r.kind in TEARDOWN), key=lambda r: TEARDOWN.index(r.kind))
        for res in doomed:
            self.api(f"delete {res.kind}", self.cloud.delete, res.id)
        return [f"{r.kind} {r.name}" for r in doomed]

    def close(self) -> None:
        pass  # no connection to close

    # -- images ---------------------------------------------------------------------------------
    def _snapshot(self, image: Resource) -> SnapshotRecord:
        return SnapshotRecord(id=image.id, name=image.name, created=image.data["created"],
                              source=image.labels.get(LABEL_ROBOT) or "build")

    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        inst = self.transport.instance(robot)
        # A builder's image is a build, not a robot's clone: no robot label, source "build".
        source = robot if inst.labels.get(LABEL_ROLE) == "clone" else None
        return self._snapshot(self.api("capture instance", self.cloud.capture, inst.id, name,
                                       owner_labels(self.fleet, "snapshot", source)))

    def list_snapshots(self) -> list[SnapshotRecord]:
        return sorted((self._snapshot(i) for i in self._owned("image")), key=lambda s: s.created)

    def delete_snapshot(self, snapshot_id: str) -> None:
        image = next((i for i in self._owned("image") if snapshot_id in (i.id, i.name)), None)
        if image is None:
            raise CcrpError(f"snapshot {snapshot_id} not found among fleet {self.fleet!r}'s", hint="ccrp snapshot list")
        self.api("delete image", self.cloud.delete, image.id)

    def has_image(self, image: str) -> bool:
        # Any image of the cloud: the fleet's snapshots, and the base images it offers.
        return any(image in (i.id, i.name) for i in self.api("list images", self.cloud.describe, "image"))

    def resolve_image(self, image: str) -> str:
        return image  # images are named directly

    # -- housekeeping ---------------------------------------------------------------------------
    def stop_note(self, robot: str) -> str | None:
        found = self._owned("instance", robot, "clone")
        return autostop_note("\n".join(found[0].data["console"])) if found else None

    def list_owned(self) -> list[OwnedResource]:
        return with_roles((OwnedResource(kind=r.kind, id=r.id, name=r.name, robot=r.labels.get(LABEL_ROBOT))
                           for r in self._owned()), ROLES)

    def delete_owned(self, resource: OwnedResource) -> None:
        res = self.api(f"get {resource.kind}", self.cloud.get, resource.id)
        if res.labels.get(LABEL_FLEET) != self.fleet:  # checked again: never delete what is not ours
            raise CcrpError(f"{resource.kind} {resource.id} is not fleet {self.fleet!r}'s; not deleting it")
        self.api(f"delete {resource.kind}", self.cloud.delete, res.id)

    def leftovers(self) -> list[str]:
        return [f"{r.kind} {r.name}" for r in self._owned() if r.kind != "image"]

    def login_keys(self) -> None:
        return None  # no login user: the transport is the cloud's API

    def check_credentials(self) -> str:
        return "the memory cloud of this process (tests only)"

    def quotas(self, robots=()) -> list[Quota]:
        live = self.api("list instances", self.cloud.describe, "instance")
        return [Quota(name="instances", scope="memory cloud", limit=self.inv.provider.max_instances,  # type: ignore[union-attr]
                      used=len(live), per_clone=1.0)]

    # -- Ability.BAKE (base.Bake) ---------------------------------------------------------------
    def console_output(self, robot: str) -> str:
        found = self._owned("instance", robot)
        return "\n".join(found[0].data["console"]) if found else ""

    def connect(self, robot: str, rec: CloneRecord, timeout: float = 300) -> None:
        """Nothing to open: the transport reaches a running instance by its labels. It must run."""
        self.transport.instance(robot)
