"""GCE clones: one VM per robot on the fleet's VPC subnetwork (the common network), forwarding its
robot's VPN subnet through a route whose next hop is the instance. Behind the fleet's entry gateway
(provider.entry: gateway, the default) a clone has no external address: the gateway, a VM of role
"gateway", holds the fleet's one reserved regional address, forwards each robot's port to its clone
and is the clones' way out (a route 0.0.0.0/0 to it for the clones' network tag). Per clone, each
clone is reachable from the internet only on the VPN port (and SSH from the operator's CIDR) at a
reserved external address of its own (kept across stop/start: the robot's bundle dials it).

Every SDK call goes through the client (client.py: retry.call, the SDK's own retry switched off),
every mutation waits for its ExtendedOperation, and every SDK failure leaves as a one-line CcrpError.
This class is the instances' lifecycle; it composes the client, the fleet's network (network.py),
its images (images.py) and what the fleet owns (owned.py).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...templates import static
from ...retry import across_zones
from ..base import GATEWAY, GATEWAY_ROLE, LABEL_ROBOT, CloneRecord, CloneSpec, CloneState, Origin, OwnedResource, Quota, SnapshotRecord, owner_labels
from ..cloud import SSH_USER, CloudProvider
from . import INFO, images, network, owned
from .client import Clients, GcpClient
from .errors import as_ccrp_error
from .ownership import description_marks, request_id, same_resource

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
# The entry gateway's route for the clones' way out: above GCE's default internet route (1000),
# which the gateway itself (not tagged as a clone) keeps.
EGRESS_PRIORITY = 900


def cpu_metric(machine_type: str) -> str:
    """The regional quota a machine type's vCPUs count against."""
    family = machine_type.split("-")[0].lower()
    return "CPUS" if family in CPUS_FAMILIES else f"{family.upper()}_CPUS"


# GCE's instance states in ccrp's words (TERMINATED is GCE's "stopped").
STATES = {"PROVISIONING": CloneState.PENDING, "STAGING": CloneState.PENDING, "REPAIRING": CloneState.PENDING,
          "RUNNING": CloneState.RUNNING, "STOPPING": CloneState.STOPPING, "SUSPENDING": CloneState.STOPPING,
          "STOPPED": CloneState.STOPPED, "SUSPENDED": CloneState.STOPPED, "TERMINATED": CloneState.STOPPED}


class GcpProvider(CloudProvider):
    kind = "gcp"
    abilities = INFO.abilities
    images, owned = images, owned  # snapshots and owned resources: CloudProvider hands them the client

    def __init__(self, inv: Inventory, workdir: Path, clients: Clients | None = None) -> None:
        super().__init__(inv, workdir)
        self.client = GcpClient(inv, workdir, clients)
        self.settings = self.client.settings
        self._machine_cpus: dict[str, int] = {}  # machine type -> vCPUs

    # -- the fleet's network (network.py) ---------------------------------------------------------
    def bootstrap(self) -> None:
        network.bootstrap(self.client)

    # -- instances --------------------------------------------------------------------------
    def _zones(self, robot: str) -> list[str]:
        override = self.inv.robot(robot)
        return [override.zone] if override and override.zone else list(self.settings.zones)

    def _machine_type(self, robot: str) -> str:
        if robot == GATEWAY:
            return self.settings.gateway_machine_type
        override = self.inv.robot(robot)
        return (override and override.instance_type) or self.settings.machine_type

    def _image_source(self, image: str) -> dict:
        """spec.image as the insert request needs it: a machine image, an image URL/path
        (projects/debian-cloud/global/images/family/debian-12) or an image of the project."""
        c = self.client
        if image.startswith("machineImages/"):
            return {"source_machine_image": f"projects/{c.project}/global/{image}"}
        if "/machineImages/" in image:
            return {"source_machine_image": image}
        return {"source_image": image if "/" in image else f"projects/{c.project}/global/images/{image}"}

    def _public(self, spec: CloneSpec) -> bool:
        """Whether the instance has an external address: a clone behind an entry gateway has none
        (its robot comes through the gateway's)."""
        return spec.role != "clone" or self.settings.entry != "gateway"

    def _tag(self, spec: CloneSpec) -> str:
        """Its network tag: the clones' (their firewall rules, routes); behind an entry gateway what
        has an external address (the gateway, a bake's builder) the gateway's, so the clones' way out
        through the gateway is not its way and SSH reaches it from the operator."""
        names = self.client.names
        return names.gateway_tag if self.settings.entry == "gateway" and spec.role != "clone" else names.tag

    def instance_resource(self, spec: CloneSpec, zone: str, user_data: str, nat_ip: str = ""):
        c = self.client
        gce = c.compute
        labels = owner_labels(self.fleet, spec.role, spec.robot)
        source = self._image_source(spec.image)
        disks = [] if "source_machine_image" in source else [gce.AttachedDisk(
            boot=True, auto_delete=True,
            initialize_params=gce.AttachedDiskInitializeParams(source_image=source["source_image"], labels=labels))]
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
        return gce.Instance(
            name=c.names.instance(spec.robot, spec.role),
            machine_type=f"zones/{zone}/machineTypes/{self._machine_type(spec.robot)}",
            labels=labels,
            tags=gce.Tags(items=[self._tag(spec)]),
            can_ip_forward=True,  # the clone routes its robot's VPN subnet, the gateway the clones' way out
            metadata=gce.Metadata(items=[gce.Items(key=k, value=v) for k, v in metadata.items()]),
            network_interfaces=[gce.NetworkInterface(
                subnetwork=network.subnetwork(c), network_i_p=spec.common_ip,
                access_configs=[self._access_config(nat_ip)] if self._public(spec) else [])],
            disks=disks,
            # No service account: nothing on a clone needs the GCP API.
        )

    def _access_config(self, nat_ip: str = ""):
        c = self.client
        # With nat_i_p, the access config uses that reserved address; without one GCE would give
        # an ephemeral IP, released at every stop and replaced at the next start.
        return c.compute.AccessConfig(name="public", type_="ONE_TO_ONE_NAT", nat_i_p=nat_ip or None)

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Create (or reuse) the robot's clone, its reserved external address (none behind an entry
        gateway) and its VPN route, or the entry gateway (role "gateway"), the fleet's address and
        the clones' way out; on failure, delete what this attempt created."""
        c = self.client
        payload, _ = INFO.fit_user_data(spec.user_data)  # before any API call
        name = c.names.instance(spec.robot, spec.role)
        with c.errors(f"clone {name}"):
            found = c.find(spec.robot, spec.role)
            if found is not None:
                return self._complete(spec, found[0], found[1].name, created=False)
            address, reserved = self._ensure_address(spec) if self._public(spec) else ("", False)
            try:
                zone, inst = across_zones(self._zones(spec.robot),
                                          lambda z: self._create_instance(spec, z, payload.decode(), address),
                                          classify=c.classify_error, what=f"create clone {name}")
                return self._complete(spec, zone, inst, created=True, address=address)
            except BaseException:
                if reserved:  # the instance is gone already (_create_instance / _complete rolled it back)
                    self._release_address(spec.robot, c.names.address(spec.robot, spec.role))
                raise

    def _create_instance(self, spec: CloneSpec, zone: str, user_data: str, nat_ip: str = ""):
        c = self.client
        resource = self.instance_resource(spec, zone, user_data, nat_ip)
        source = self._image_source(spec.image)
        request = c.compute.InsertInstanceRequest(
            project=c.project, zone=zone, instance_resource=resource,
            source_machine_image=source.get("source_machine_image", ""),
            request_id=request_id(spec.instance_id, zone))
        what = f"create instance {resource.name} in {zone}"
        op = c.mutate(what, c.clients.instances.insert, request=request)
        try:
            # GCE remembers request ids for about an hour: a clone deleted and re-created in that
            # time gets the earlier (done) operation back and no instance. Send it again under an
            # id derived from that operation (still stable if this call is retried). A clone
            # re-created more than once in the hour meets each earlier operation in turn.
            replays = 0
            while c.get("instance", c.clients.instances.get, project=c.project, zone=zone,
                            instance=resource.name) is None:
                if replays == MAX_REPLAYS:
                    raise CcrpError(f"{what}: GCE answered {replays} earlier operations and created no instance",
                                    hint="wait an hour (GCE forgets request ids) or give the robot another name")
                replays += 1
                again = c.compute.InsertInstanceRequest(request, request_id=request_id(spec.instance_id, zone, op.name))
                op = c.mutate(what, c.clients.instances.insert, request=again)
        except BaseException:
            self._rollback(spec.robot, zone, resource.name, route=False)
            raise
        return zone, resource.name

    def _complete(self, spec: CloneSpec, zone: str, name: str, created: bool, address: str = "") -> CloneRecord:
        c = self.client
        route_created = False
        origin = Origin.CREATED if created else Origin.REUSED
        try:
            inst = c.call("get instance", c.clients.instances.get, project=c.project, zone=zone, instance=name)
            if inst.status == "TERMINATED":  # GCE's word for stopped: a reused clone someone stopped
                c.mutate(f"start instance {name}", c.clients.instances.start, project=c.project, zone=zone,
                             instance=name)
                origin = Origin.RESUMED
                inst = c.call("get instance", c.clients.instances.get, project=c.project, zone=zone,
                                  instance=name)
            if not self._public(spec):
                if not created:  # kept from per-clone days: its robot comes through the gateway now
                    self._give_back_address(spec, zone, inst)
            elif not address:  # a reused clone: make sure it answers at its reserved address
                self._keep_address(spec, zone, inst)
            route_created = self._ensure_route(spec, inst)
            inst = c.call("get instance", c.clients.instances.get, project=c.project, zone=zone, instance=name)
        except BaseException as exc:
            self._rollback(spec.robot, zone, name if created else None, route_created)
            if isinstance(exc, Exception):
                raise as_ccrp_error(f"clone {name}", exc, c.region) from exc
            raise
        return self._record(spec.robot, inst, origin)

    def _rollback(self, robot: str, zone: str, instance: str | None, route: bool) -> None:
        """Delete what one failed attempt created; a failure here is logged, never masks the cause."""
        c = self.client
        try:
            ops = []
            if route:
                ops.append(("delete route", c.delete("route", c.clients.routes.delete, project=c.project,
                                                         route=c.names.route(robot))))
            if instance:
                ops.append(("delete instance", c.delete("instance", c.clients.instances.delete, project=c.project,
                                                            zone=zone, instance=instance)))
            c.wait_all(ops)
        except Exception as exc:  # noqa: BLE001
            log.warning("rollback of clone %s incomplete (%s); `ccrp gc` will find the leftovers", robot, exc)

    # -- reserved external address ----------------------------------------------------------
    def _ensure_address(self, spec: CloneSpec, current: str = "") -> tuple[str, bool]:
        """(IP, created by this call) of the instance's reserved regional external address. When
        missing it is reserved; with `current` (the ephemeral IP a clone of an earlier ccrp runs
        at) that IP is promoted to a reserved one, so the robot's installed bundle keeps working."""
        c = self.client
        name = c.names.address(spec.robot, spec.role)
        have = c.get("address", c.clients.addresses.get, project=c.project, region=c.region, address=name)
        created = have is None
        if have is None:
            resource = c.compute.Address(name=name, address_type="EXTERNAL", address=current or None,
                                            description=c.names.describe("address", spec.robot))
            # A Conflict here is this call's own insert that went through before a retry: it is
            # still this attempt's to roll back (the ownership check below catches a foreign one).
            c.insert(f"address {name}", c.clients.addresses.insert, project=c.project, region=c.region,
                         address_resource=resource)
            have = c.call("get address", c.clients.addresses.get, project=c.project, region=c.region,
                              address=name)
        if not c.names.owns_unlabelled(have.name, have.description):
            raise CcrpError(f"address {name} exists in {c.region} but is not ccrp's", hint="rename or release it")
        return have.address, created

    def _keep_address(self, spec: CloneSpec, zone: str, inst) -> None:
        """A reused clone runs at its reserved address. One without an address (made by a ccrp that
        did not reserve them, or its address released by hand) has its current IP promoted, the
        IP its robot's bundle dials; one at another IP than its existing address (its access
        config changed by hand) gets an access config on the address."""
        c = self.client
        nic = inst.network_interfaces[0]
        current = nic.access_configs[0].nat_i_p if nic.access_configs else ""
        address, _ = self._ensure_address(spec, current)
        if current == address:
            return
        where = dict(project=c.project, zone=zone, instance=inst.name, network_interface=nic.name or "nic0")
        if nic.access_configs:
            c.mutate(f"remove the external IP {current} of {inst.name}", c.clients.instances.delete_access_config,
                         access_config=nic.access_configs[0].name, **where)
        c.mutate(f"attach address {address} to {inst.name}", c.clients.instances.add_access_config,
                     access_config_resource=self._access_config(address), **where)

    def _give_back_address(self, spec: CloneSpec, zone: str, inst) -> None:
        """A clone behind an entry gateway has no external IP: one it holds goes, and its reserved
        address is released (the gateway's is the fleet's one)."""
        c = self.client
        nic = inst.network_interfaces[0]
        if nic.access_configs:
            c.mutate(f"remove the external IP of {inst.name}", c.clients.instances.delete_access_config,
                     project=c.project, zone=zone, instance=inst.name, network_interface=nic.name or "nic0",
                     access_config=nic.access_configs[0].name)
        self._release_addresses(spec.robot)

    def _release_addresses(self, robot: str) -> None:
        """Release the robot's reserved addresses (once no instance uses them: GCE refuses before)."""
        c = self.client
        c.wait_all([(f"release address {a.name}", c.delete(f"address {a.name}", c.clients.addresses.delete,
                                                           project=c.project, region=c.region, address=a.name))
                    for a in self._addresses(robot)])

    def _addresses(self, robot: str | None = None) -> list:
        """The fleet's reserved addresses in the region (of one robot)."""
        c = self.client
        found = c.list("addresses", c.clients.addresses.list, project=c.project, region=c.region)
        return [a for a in found if c.names.owns_unlabelled(a.name, a.description)
                and (robot is None or description_marks(a.description).get(LABEL_ROBOT) == robot)]

    def _release_address(self, robot: str, name: str) -> None:
        """Rollback's release of an address this attempt reserved; a failure is logged, never
        masks the cause (`ccrp gc` finds the address)."""
        c = self.client
        try:
            c.wait_all([(f"release address {name}", c.delete(f"address {name}", c.clients.addresses.delete,
                                                                     project=c.project, region=c.region,
                                                                     address=name))])
        except Exception as exc:  # noqa: BLE001
            log.warning("rollback of clone %s: address %s not released (%s); `ccrp gc` will find it", robot, name, exc)

    def _ensure_route(self, spec: CloneSpec, inst) -> bool:
        """Route the robot's VPN subnet to its clone, or (the entry gateway) the clones' way out to
        the internet through the gateway: GCE gives an instance without an external IP none, and a
        gateway made again is another next hop. True when this call created the route."""
        c = self.client
        gateway = spec.role == GATEWAY_ROLE
        dest, priority, tags = ("0.0.0.0/0", EGRESS_PRIORITY, [c.names.tag]) if gateway else (spec.vpn_subnet, 1000, [])
        if not dest:
            return False
        name = c.names.route(spec.robot)
        have = c.get("route", c.clients.routes.get, project=c.project, route=name)
        if have is not None:
            if not c.names.owns_unlabelled(have.name, have.description):
                raise CcrpError(f"route {name} exists but is not ccrp's", hint="rename or remove it")
            same = (have.dest_range, list(have.tags)) == (dest, tags)
            if same and same_resource(have.next_hop_instance, inst.self_link):
                return False
            # Left by an earlier clone of this robot (other zone / subnet) or gateway: replace it.
            c.wait_all([("delete route", c.delete("route", c.clients.routes.delete, project=c.project,
                                                           route=name))])
        route = c.compute.Route(
            name=name, network=inst.network_interfaces[0].network, dest_range=dest, tags=tags,
            next_hop_instance=inst.self_link, priority=priority, description=c.names.describe("route", spec.robot))
        return c.insert(f"route {name}", c.clients.routes.insert, project=c.project, route_resource=route)

    def _record(self, robot: str, inst, origin: Origin | None = None) -> CloneRecord:
        nic = inst.network_interfaces[0] if inst.network_interfaces else None
        public = nic.access_configs[0].nat_i_p if nic and nic.access_configs else ""
        return CloneRecord(robot=robot, provider_id=str(inst.id), state=CloneState.of(inst.status, STATES),
                           status=inst.status, public_ip=public or None,
                           common_ip=(nic.network_i_p if nic else "") or None, origin=origin)

    def gateway(self) -> CloneRecord | None:
        """The fleet's entry gateway: the instance of role "gateway" (its reserved address, the
        fleet's, stays when the instance goes and is given to the next one)."""
        c = self.client
        with c.errors("find the entry gateway"):
            found = c.find(GATEWAY, GATEWAY_ROLE)
            return self._record(GATEWAY, found[1]) if found is not None else None

    def query(self) -> dict[str, CloneRecord]:
        c = self.client
        with c.errors("list clones"):
            clones = ((dict(inst.labels).get(LABEL_ROBOT), inst) for _zone, inst in c.instances("clone"))
            return {robot: self._record(robot, inst) for robot, inst in clones if robot}

    def stop_instance(self, robot: str) -> bool:
        c = self.client
        with c.errors(f"stop clone of {robot}"):
            found = c.find(robot)
            if found is None or found[1].status not in ("PROVISIONING", "STAGING", "RUNNING"):
                return False
            zone, inst = found
            c.mutate(f"stop instance {inst.name}", c.clients.instances.stop, project=c.project, zone=zone,
                         instance=inst.name)
            return True

    def terminate(self, robot: str) -> bool:
        """Delete the robot's clone, its route and then its reserved address (owned only); the
        entry gateway's firewall rules go with it (the fleet went back to per-clone). False when
        there was no clone."""
        c = self.client
        with c.errors(f"delete clone of {robot}"):
            route = c.get("route", c.clients.routes.get, project=c.project, route=c.names.route(robot))
            ops = []
            if route is not None and c.names.owns_unlabelled(route.name, route.description):
                ops.append(("delete route", c.delete("route", c.clients.routes.delete, project=c.project,
                                                         route=route.name)))
            if robot == GATEWAY:  # only the gateway's rules carry a robot's mark (network.firewall_rules)
                ops += [(f"delete firewall {rule.name}", c.delete(f"firewall {rule.name}", c.clients.firewalls.delete,
                                                                 project=c.project, firewall=rule.name))
                        for rule in c.list("firewalls", c.clients.firewalls.list, project=c.project)
                        if c.names.owns_unlabelled(rule.name, rule.description)
                        and description_marks(rule.description).get(LABEL_ROBOT) == robot]
            found = c.find(robot, role=None)
            if found is not None:
                zone, inst = found
                ops.append(("delete instance", c.delete("instance", c.clients.instances.delete,
                                                            project=c.project, zone=zone, instance=inst.name)))
            c.wait_all(ops)
            self._release_addresses(robot)  # after the instance: GCE refuses to release an address in use
            return found is not None

    def console_output(self, robot: str) -> str:
        c = self.client
        with c.errors(f"console of clone {robot}"):
            zone, inst = c.require(robot)
            out = c.call("get serial port output", c.clients.instances.get_serial_port_output,
                             project=c.project, zone=zone, instance=inst.name)
            return out.contents

    # -- doctor -----------------------------------------------------------------------------
    def check_credentials(self) -> str:
        """ADC resolve and one cheap read of the fleet's region."""
        c = self.client
        with c.errors(f"check access to project {c.project}"):
            region = c.call("get region", c.clients.regions.get, project=c.project, region=c.region)
            return f"project {c.project}, region {region.name}: {region.status}"

    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]:
        """The region's quotas a clone draws on (regions.get: GCE's own limit and usage), with
        what the clones of `robots` take: an instance, its machine type's vCPUs (CPUS, or the
        family's own quota: N2_CPUS...), an external IP in use and a reserved one (none for a
        robot whose address is reserved already). Behind an entry gateway a clone takes no address;
        the gateway, while there is none, takes one instance of provider.gateway_machine_type, one IP in
        use and (while the fleet's is not reserved) one reserved address, however many clones."""
        c = self.client
        with c.errors(f"quotas of {c.region}"):
            region = c.call("get region", c.clients.regions.get, project=c.project, region=c.region)
            reserved = {a.name for a in self._addresses()} if robots else set()
            machine = {r: self._machine_type(r) for r in robots}
            default, gateway_type = self.settings.machine_type, self._machine_type(GATEWAY)
            gateway = self.settings.entry == "gateway"
            making = 1.0 if gateway and robots and c.find(GATEWAY, GATEWAY_ROLE) is None else 0.0
            address = 0.0 if c.names.address(GATEWAY, GATEWAY_ROLE) in reserved else making

            def cpus(machine_type: str, metric: str) -> float:
                return float(self._vcpus(machine_type)) if cpu_metric(machine_type) == metric else 0.0

            found = []
            each: dict[str, float]
            for q in region.quotas:
                if q.metric == "INSTANCES":
                    per, each, once = 1.0, {}, making
                elif q.metric == "IN_USE_ADDRESSES":
                    per, each, once = (0.0 if gateway else 1.0), {}, making
                elif q.metric == "STATIC_ADDRESSES":
                    per, once = (0.0 if gateway else 1.0), address
                    each = {} if gateway else {r: 0.0 for r in robots if c.names.address(r) in reserved}
                elif q.metric.endswith("CPUS") and q.metric != "CPUS_ALL_REGIONS":
                    per = cpus(default, q.metric)
                    each = {r: n for r, m in machine.items() if (n := cpus(m, q.metric)) != per}
                    once = cpus(gateway_type, q.metric) if making else 0.0  # looked up only when it is made
                    if not per and not each and not once:
                        continue  # another family's CPUs: none of these clones draws on it
                else:
                    continue
                found.append(Quota(
                    name=q.metric, scope=f"region {c.region}", limit=q.limit, used=q.usage, per_clone=per,
                    per_robot=each, once=once,
                    hint=f"request more in the console: IAM & Admin > Quotas, {q.metric} in {c.region}"))
            return found

    def _vcpus(self, machine_type: str) -> int:
        """The machine type's vCPUs, looked up once per type."""
        c = self.client
        if machine_type not in self._machine_cpus:
            zone = self.settings.zones[0]
            self._machine_cpus[machine_type] = c.call(
                "get machine type", c.clients.machine_types.get, project=c.project, zone=zone,
                machine_type=machine_type).guest_cpus
        return self._machine_cpus[machine_type]
