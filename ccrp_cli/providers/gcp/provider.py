"""GCE clones: one VM per robot on the fleet's VPC subnetwork (the common network), reachable
from the internet only on the VPN port (and SSH from the operator's CIDR) at a reserved regional
external address of its own (kept across stop/start: the robot's bundle dials it), forwarding its
robot's VPN subnet through a route whose next hop is the instance.

Every SDK call goes through self.api (retry.call, the SDK's own retry switched off), every
mutation waits for its ExtendedOperation, and every SDK failure leaves as a one-line CcrpError.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...templates import static
from ...retry import ErrorClass, across_zones
from ..base import (LABEL_ROBOT, CloneRecord, CloneSpec, CloneState, Origin, Quota,
                    owner_labels)
from ..cloud import SSH_USER, CloudProvider
from . import INFO
from .clients import Clients, sdk
from .errors import as_ccrp_error, classify
from .images import Images
from .network import Network
from .owned import Owned
from .ownership import Names, description_marks, request_id, same_resource, tail
from .settings import GcpSettings

log = logging.getLogger(__name__)

# Earlier operations an insert may meet under its request ids (one per re-creation of the clone
# within GCE's hour of remembering them) before it sends one GCE has not seen.
MAX_REPLAYS = 20
# Where Debian publishes its GCE images (the bake's default base, INFO.bake_base). They run
# the Google guest agent instead of cloud-init, so an instance booted from one gets a startup-script
# (templates/gcp/startup-script) that installs cloud-init; a baked snapshot has it already.
STOCK_IMAGES = "projects/debian-cloud/"
# Machine families whose vCPUs count against the regional CPUS quota; every other family has a
# quota of its own (N2_CPUS, C3_CPUS...).
CPUS_FAMILIES = ("e2", "n1", "f1", "g1", "custom")


def cpu_metric(machine_type: str) -> str:
    """The regional quota a machine type's vCPUs count against."""
    family = machine_type.split("-")[0].lower()
    return "CPUS" if family in CPUS_FAMILIES else f"{family.upper()}_CPUS"


# GCE's instance states in ccrp's words (TERMINATED is GCE's "stopped").
STATES = {"PROVISIONING": CloneState.PENDING, "STAGING": CloneState.PENDING, "REPAIRING": CloneState.PENDING,
          "RUNNING": CloneState.RUNNING, "STOPPING": CloneState.STOPPING, "SUSPENDING": CloneState.STOPPING,
          "STOPPED": CloneState.STOPPED, "SUSPENDED": CloneState.STOPPED, "TERMINATED": CloneState.STOPPED}


class GcpProvider(Network, Images, Owned, CloudProvider):
    kind = "gcp"
    abilities = INFO.abilities
    op_timeout = 600.0  # seconds to wait for one GCE operation

    def __init__(self, inv: Inventory, workdir: Path, clients: Clients | None = None) -> None:
        super().__init__(inv, workdir)
        self.compute = sdk()
        from google.api_core import exceptions

        self._NotFound, self._Conflict = exceptions.NotFound, exceptions.Conflict
        self.settings = cast(GcpSettings, inv.provider)  # get_provider picked this backend by these settings' kind
        self.project, self.region = self.settings.project, self.settings.region
        self.names = Names(self.fleet)
        self._clients = clients
        self._lock = threading.Lock()
        self._subnet_link: str | None = None
        self._machine_cpus: dict[str, int] = {}  # machine type -> vCPUs

    @property
    def c(self) -> Clients:
        with self._lock:  # clones are created from parallel threads
            if self._clients is None:
                self._clients = Clients.connect()
            return self._clients

    # -- calls ------------------------------------------------------------------------------
    def classify_error(self, exc: BaseException) -> ErrorClass:
        return classify(exc)

    def _call(self, what: str, method, *args, **kwargs):
        """One SDK call through retry.call; the SDK's own retry is off so there is one policy."""
        return self.api(what, method, *args, retry=None, **kwargs)

    def _list(self, what: str, method, *args, **kwargs) -> list:
        """Every item of a paged list: later pages are fetched inside the retried call too."""
        return self.api(what, lambda: list(method(*args, retry=None, **kwargs)))

    def _get(self, what: str, method, **kwargs):
        try:
            return self._call(f"get {what}", method, **kwargs)
        except self._NotFound:
            return None

    def _wait(self, op, what: str) -> None:
        """Until the operation is done. A failed poll (503, connection reset) polls again under
        retry.call; the operation's own error is raised as it is, for the caller to classify
        (zone fallback, rollback). Warnings (e.g. a disk larger than its image) are logged."""
        self.api(f"wait for {what}", op.result, timeout=self.op_timeout,
                 classify=lambda exc: ErrorClass.FATAL if op.error_code else classify(exc))
        if op.error_code:  # result() raises for these; kept as a guard if a future SDK does not
            raise CcrpError(f"{what}: operation {op.name} failed ({op.error_code} {op.error_message})")
        for warning in getattr(op, "warnings", None) or []:
            log.warning("%s: %s %s", what, warning.code, warning.message)

    def _mutate(self, what: str, method, *args, **kwargs):
        op = self._call(what, method, *args, **kwargs)
        self._wait(op, what)
        return op

    def _insert(self, what: str, method, **kwargs) -> bool:
        """Create a resource named by the caller; False when it exists already (a retried call
        that had gone through, or a parallel run)."""
        try:
            self._mutate(f"create {what}", method, **kwargs)
            return True
        except self._Conflict:
            return False

    def _delete(self, what: str, method, **kwargs):
        """Start a delete; None when the resource is already gone. The caller waits."""
        try:
            return self._call(f"delete {what}", method, **kwargs)
        except self._NotFound:
            return None

    def _wait_all(self, ops: list[tuple[str, object]]) -> None:
        for what, op in ops:
            if op is not None:
                try:
                    self._wait(op, what)
                except self._NotFound:
                    pass

    @contextmanager
    def _errors(self, what: str):
        """SDK failures leave the provider as one-line CcrpErrors with a hint."""
        try:
            yield
        except CcrpError:
            raise
        except Exception as exc:  # noqa: BLE001 - every SDK error class
            raise as_ccrp_error(what, exc, self.region) from exc

    # -- instances --------------------------------------------------------------------------
    def _zones(self, robot: str) -> list[str]:
        override = self.inv.robot(robot)
        return [override.zone] if override and override.zone else list(self.settings.zones)

    def _machine_type(self, robot: str) -> str:
        override = self.inv.robot(robot)
        return (override and override.instance_type) or self.settings.machine_type

    def _instances(self, role: str | None = None, robot: str | None = None) -> list[tuple[str, Any]]:
        """(zone, instance) of every instance carrying the fleet's labels (and role / robot); the
        instance is the SDK's compute_v1.Instance, which mypy does not read (pyproject.toml)."""
        request = self.compute.AggregatedListInstancesRequest(
            project=self.project, filter=self.names.label_filter(role, robot))
        found = []
        for _scope, scoped in self._list("instances", self.c.instances.aggregated_list, request=request):
            for inst in scoped.instances:
                labels = dict(inst.labels)
                if self.names.owns_labels(labels) and (robot is None or labels.get(LABEL_ROBOT) == robot):
                    found.append((tail(inst.zone), inst))
        return found

    def _find(self, robot: str, role: str | None = "clone"):
        """The robot's instance; role None finds the builder of `snapshot bake` too."""
        return next(iter(self._instances(role, robot)), None)

    def _image_source(self, image: str) -> dict:
        """spec.image as the insert request needs it: a machine image, an image URL/path
        (projects/debian-cloud/global/images/family/debian-12) or an image of the project."""
        if image.startswith("machineImages/"):
            return {"source_machine_image": f"projects/{self.project}/global/{image}"}
        if "/machineImages/" in image:
            return {"source_machine_image": image}
        return {"source_image": image if "/" in image else f"projects/{self.project}/global/images/{image}"}

    def instance_resource(self, spec: CloneSpec, zone: str, user_data: str, nat_ip: str = ""):
        c = self.compute
        labels = owner_labels(self.fleet, spec.role, spec.robot)
        source = self._image_source(spec.image)
        disks = [] if "source_machine_image" in source else [c.AttachedDisk(
            boot=True, auto_delete=True,
            initialize_params=c.AttachedDiskInitializeParams(source_image=source["source_image"], labels=labels))]
        metadata = {
            "user-data": user_data,
            # The login user the user-data creates (SSH_USER), with the fleet's public key: the guest
            # agent of Debian's GCE images reads this entry too. No private key in any metadata.
            "ssh-keys": f"{SSH_USER}:{self.operator_public_key()}",
            # ssh-keys metadata is ignored under OS Login; ccrp logs in with its own fleet key.
            "enable-oslogin": "FALSE",
        }
        if STOCK_IMAGES in spec.image:
            # Debian's GCE images have no cloud-init: this installs it and runs the user-data above.
            metadata["startup-script"] = static("gcp/startup-script")
        return c.Instance(
            name=self.names.instance(spec.robot, spec.role),
            machine_type=f"zones/{zone}/machineTypes/{self._machine_type(spec.robot)}",
            labels=labels,
            tags=c.Tags(items=[self.names.tag]),
            can_ip_forward=True,  # the clone routes its robot's VPN subnet
            metadata=c.Metadata(items=[c.Items(key=k, value=v) for k, v in metadata.items()]),
            network_interfaces=[c.NetworkInterface(
                subnetwork=self._subnetwork(), network_i_p=spec.common_ip,
                access_configs=[self._access_config(nat_ip)])],
            disks=disks,
            # No service account: nothing on a clone needs the GCP API.
        )

    def _access_config(self, nat_ip: str = ""):
        # With nat_i_p, the access config uses that reserved address; without one GCE would give
        # an ephemeral IP, released at every stop and replaced at the next start.
        return self.compute.AccessConfig(name="public", type_="ONE_TO_ONE_NAT", nat_i_p=nat_ip or None)

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Create (or reuse) the robot's clone, its reserved external address and its VPN route;
        on failure, delete what this attempt created."""
        payload, _ = INFO.fit_user_data(spec.user_data)  # before any API call
        name = self.names.instance(spec.robot, spec.role)
        with self._errors(f"clone {name}"):
            found = self._find(spec.robot, spec.role)
            if found is not None:
                return self._complete(spec, found[0], found[1].name, created=False)
            address, reserved = self._ensure_address(spec)
            try:
                zone, inst = across_zones(self._zones(spec.robot),
                                          lambda z: self._create_instance(spec, z, payload.decode(), address),
                                          classify=self.classify_error, what=f"create clone {name}")
                return self._complete(spec, zone, inst, created=True, address=address)
            except BaseException:
                if reserved:  # the instance is gone already (_create_instance / _complete rolled it back)
                    self._release_address(spec.robot, self.names.address(spec.robot, spec.role))
                raise

    def _create_instance(self, spec: CloneSpec, zone: str, user_data: str, nat_ip: str = ""):
        resource = self.instance_resource(spec, zone, user_data, nat_ip)
        source = self._image_source(spec.image)
        request = self.compute.InsertInstanceRequest(
            project=self.project, zone=zone, instance_resource=resource,
            source_machine_image=source.get("source_machine_image", ""),
            request_id=request_id(spec.instance_id, zone))
        what = f"create instance {resource.name} in {zone}"
        op = self._mutate(what, self.c.instances.insert, request=request)
        try:
            # GCE remembers request ids for about an hour: a clone deleted and re-created in that
            # time gets the earlier (done) operation back and no instance. Send it again under an
            # id derived from that operation (still stable if this call is retried). A clone
            # re-created more than once in the hour meets each earlier operation in turn.
            replays = 0
            while self._get("instance", self.c.instances.get, project=self.project, zone=zone,
                            instance=resource.name) is None:
                if replays == MAX_REPLAYS:
                    raise CcrpError(f"{what}: GCE answered {replays} earlier operations and created no instance",
                                    hint="wait an hour (GCE forgets request ids) or give the robot another name")
                replays += 1
                again = self.compute.InsertInstanceRequest(request, request_id=request_id(spec.instance_id, zone, op.name))
                op = self._mutate(what, self.c.instances.insert, request=again)
        except BaseException:
            self._rollback(spec.robot, zone, resource.name, route=False)
            raise
        return zone, resource.name

    def _complete(self, spec: CloneSpec, zone: str, name: str, created: bool, address: str = "") -> CloneRecord:
        route_created = False
        origin = Origin.CREATED if created else Origin.REUSED
        try:
            inst = self._call("get instance", self.c.instances.get, project=self.project, zone=zone, instance=name)
            if inst.status == "TERMINATED":  # GCE's word for stopped: a reused clone someone stopped
                self._mutate(f"start instance {name}", self.c.instances.start, project=self.project, zone=zone,
                             instance=name)
                origin = Origin.RESUMED
                inst = self._call("get instance", self.c.instances.get, project=self.project, zone=zone,
                                  instance=name)
            if not address:  # a reused clone: make sure it answers at its reserved address
                self._keep_address(spec, zone, inst)
            route_created = self._ensure_route(spec, inst)
            inst = self._call("get instance", self.c.instances.get, project=self.project, zone=zone, instance=name)
        except BaseException as exc:
            self._rollback(spec.robot, zone, name if created else None, route_created)
            if isinstance(exc, Exception):
                raise as_ccrp_error(f"clone {name}", exc, self.region) from exc
            raise
        return self._record(spec.robot, inst, origin)

    def _rollback(self, robot: str, zone: str, instance: str | None, route: bool) -> None:
        """Delete what one failed attempt created; a failure here is logged, never masks the cause."""
        try:
            ops = []
            if route:
                ops.append(("delete route", self._delete("route", self.c.routes.delete, project=self.project,
                                                         route=self.names.route(robot))))
            if instance:
                ops.append(("delete instance", self._delete("instance", self.c.instances.delete, project=self.project,
                                                            zone=zone, instance=instance)))
            self._wait_all(ops)
        except Exception as exc:  # noqa: BLE001
            log.warning("rollback of clone %s incomplete (%s); `ccrp gc` will find the leftovers", robot, exc)

    # -- reserved external address ----------------------------------------------------------
    def _ensure_address(self, spec: CloneSpec, current: str = "") -> tuple[str, bool]:
        """(IP, created by this call) of the instance's reserved regional external address. When
        missing it is reserved; with `current` (the ephemeral IP a clone of an earlier ccrp runs
        at) that IP is promoted to a reserved one, so the robot's installed bundle keeps working."""
        name = self.names.address(spec.robot, spec.role)
        have = self._get("address", self.c.addresses.get, project=self.project, region=self.region, address=name)
        created = have is None
        if have is None:
            resource = self.compute.Address(name=name, address_type="EXTERNAL", address=current or None,
                                            description=self.names.describe("address", spec.robot))
            # A Conflict here is this call's own insert that went through before a retry: it is
            # still this attempt's to roll back (the ownership check below catches a foreign one).
            self._insert(f"address {name}", self.c.addresses.insert, project=self.project, region=self.region,
                         address_resource=resource)
            have = self._call("get address", self.c.addresses.get, project=self.project, region=self.region,
                              address=name)
        if not self.names.owns_unlabelled(have.name, have.description):
            raise CcrpError(f"address {name} exists in {self.region} but is not ccrp's", hint="rename or release it")
        return have.address, created

    def _keep_address(self, spec: CloneSpec, zone: str, inst) -> None:
        """A reused clone runs at its reserved address. One without an address (made by a ccrp that
        did not reserve them, or its address released by hand) has its current IP promoted, the
        IP its robot's bundle dials; one at another IP than its existing address (its access
        config changed by hand) gets an access config on the address."""
        nic = inst.network_interfaces[0]
        current = nic.access_configs[0].nat_i_p if nic.access_configs else ""
        address, _ = self._ensure_address(spec, current)
        if current == address:
            return
        where = dict(project=self.project, zone=zone, instance=inst.name, network_interface=nic.name or "nic0")
        if nic.access_configs:
            self._mutate(f"remove the external IP {current} of {inst.name}", self.c.instances.delete_access_config,
                         access_config=nic.access_configs[0].name, **where)
        self._mutate(f"attach address {address} to {inst.name}", self.c.instances.add_access_config,
                     access_config_resource=self._access_config(address), **where)

    def _addresses(self, robot: str | None = None) -> list:
        """The fleet's reserved addresses in the region (of one robot)."""
        found = self._list("addresses", self.c.addresses.list, project=self.project, region=self.region)
        return [a for a in found if self.names.owns_unlabelled(a.name, a.description)
                and (robot is None or description_marks(a.description).get(LABEL_ROBOT) == robot)]

    def _release_address(self, robot: str, name: str) -> None:
        """Rollback's release of an address this attempt reserved; a failure is logged, never
        masks the cause (`ccrp gc` finds the address)."""
        try:
            self._wait_all([(f"release address {name}", self._delete(f"address {name}", self.c.addresses.delete,
                                                                     project=self.project, region=self.region,
                                                                     address=name))])
        except Exception as exc:  # noqa: BLE001
            log.warning("rollback of clone %s: address %s not released (%s); `ccrp gc` will find it", robot, name, exc)

    def _ensure_route(self, spec: CloneSpec, inst) -> bool:
        """Route the robot's VPN subnet to its clone; True when this call created the route."""
        if not spec.vpn_subnet:
            return False
        name = self.names.route(spec.robot)
        have = self._get("route", self.c.routes.get, project=self.project, route=name)
        if have is not None:
            if not self.names.owns_unlabelled(have.name, have.description):
                raise CcrpError(f"route {name} exists but is not ccrp's", hint="rename or remove it")
            if have.dest_range == spec.vpn_subnet and same_resource(have.next_hop_instance, inst.self_link):
                return False
            # Left by an earlier clone of this robot (other zone / subnet): replace it.
            self._wait_all([("delete route", self._delete("route", self.c.routes.delete, project=self.project,
                                                           route=name))])
        route = self.compute.Route(
            name=name, network=inst.network_interfaces[0].network, dest_range=spec.vpn_subnet,
            next_hop_instance=inst.self_link, priority=1000, description=self.names.describe("route", spec.robot))
        return self._insert(f"route {name}", self.c.routes.insert, project=self.project, route_resource=route)

    def _record(self, robot: str, inst, origin: Origin | None = None) -> CloneRecord:
        nic = inst.network_interfaces[0] if inst.network_interfaces else None
        public = nic.access_configs[0].nat_i_p if nic and nic.access_configs else ""
        return CloneRecord(robot=robot, provider_id=str(inst.id), state=CloneState.of(inst.status, STATES),
                           status=inst.status, public_ip=public or None,
                           common_ip=(nic.network_i_p if nic else "") or None, origin=origin)

    def query(self) -> dict[str, CloneRecord]:
        with self._errors("list clones"):
            clones = ((dict(inst.labels).get(LABEL_ROBOT), inst) for _zone, inst in self._instances("clone"))
            return {robot: self._record(robot, inst) for robot, inst in clones if robot}

    def stop_instance(self, robot: str) -> bool:
        with self._errors(f"stop clone of {robot}"):
            found = self._find(robot)
            if found is None or found[1].status not in ("PROVISIONING", "STAGING", "RUNNING"):
                return False
            zone, inst = found
            self._mutate(f"stop instance {inst.name}", self.c.instances.stop, project=self.project, zone=zone,
                         instance=inst.name)
            return True

    def terminate(self, robot: str) -> bool:
        """Delete the robot's clone, its route and then its reserved address (owned only); False
        when there was no clone."""
        with self._errors(f"delete clone of {robot}"):
            route = self._get("route", self.c.routes.get, project=self.project, route=self.names.route(robot))
            ops = []
            if route is not None and self.names.owns_unlabelled(route.name, route.description):
                ops.append(("delete route", self._delete("route", self.c.routes.delete, project=self.project,
                                                         route=route.name)))
            found = self._find(robot, role=None)
            if found is not None:
                zone, inst = found
                ops.append(("delete instance", self._delete("instance", self.c.instances.delete,
                                                            project=self.project, zone=zone, instance=inst.name)))
            self._wait_all(ops)
            # After the instance: GCE refuses to release an address still in use.
            self._wait_all([(f"release address {a.name}", self._delete(
                f"address {a.name}", self.c.addresses.delete, project=self.project, region=self.region,
                address=a.name)) for a in self._addresses(robot)])
            return found is not None

    def console_output(self, robot: str) -> str:
        with self._errors(f"console of clone {robot}"):
            zone, inst = self._require(robot)
            out = self._call("get serial port output", self.c.instances.get_serial_port_output,
                             project=self.project, zone=zone, instance=inst.name)
            return out.contents

    def _require(self, robot: str):
        found = self._find(robot, role=None)
        if found is None:
            raise CcrpError(f"robot {robot!r} has no clone in fleet {self.fleet}", hint=f"ccrp clone create --robot {robot}")
        return found

    # -- doctor -----------------------------------------------------------------------------
    def check_credentials(self) -> str:
        """ADC resolve and one cheap read of the fleet's region."""
        with self._errors(f"check access to project {self.project}"):
            region = self._call("get region", self.c.regions.get, project=self.project, region=self.region)
            return f"project {self.project}, region {region.name}: {region.status}"

    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]:
        """The region's quotas a clone draws on (regions.get: GCE's own limit and usage), with
        what the clones of `robots` take: an instance, its machine type's vCPUs (CPUS, or the
        family's own quota: N2_CPUS...), an external IP in use and a reserved one (none for a
        robot whose address is reserved already)."""
        with self._errors(f"quotas of {self.region}"):
            region = self._call("get region", self.c.regions.get, project=self.project, region=self.region)
            reserved = {a.name for a in self._addresses()} if robots else set()
            machine = {r: self._machine_type(r) for r in robots}
            default = self.settings.machine_type

            def cpus(machine_type: str, metric: str) -> float:
                return float(self._vcpus(machine_type)) if cpu_metric(machine_type) == metric else 0.0

            found = []
            for q in region.quotas:
                if q.metric in ("INSTANCES", "IN_USE_ADDRESSES"):
                    per, each = 1.0, {}
                elif q.metric == "STATIC_ADDRESSES":
                    per, each = 1.0, {r: 0.0 for r in robots if self.names.address(r) in reserved}
                elif q.metric.endswith("CPUS") and q.metric != "CPUS_ALL_REGIONS":
                    per = cpus(default, q.metric)
                    each = {r: n for r, m in machine.items() if (n := cpus(m, q.metric)) != per}
                    if not per and not each:
                        continue  # another family's CPUs: none of these clones draws on it
                else:
                    continue
                found.append(Quota(
                    name=q.metric, scope=f"region {self.region}", limit=q.limit, used=q.usage, per_clone=per,
                    per_robot=each,
                    hint=f"request more in the console: IAM & Admin > Quotas, {q.metric} in {self.region}"))
            return found

    def _vcpus(self, machine_type: str) -> int:
        """The machine type's vCPUs, looked up once per type."""
        if machine_type not in self._machine_cpus:
            zone = self.settings.zones[0]
            self._machine_cpus[machine_type] = self._call(
                "get machine type", self.c.machine_types.get, project=self.project, zone=zone,
                machine_type=machine_type).guest_cpus
        return self._machine_cpus[machine_type]
