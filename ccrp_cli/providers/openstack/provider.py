"""OpenStack provider: a clone is a Nova server on the fleet's common network (Neutron port
with a fixed IP and the clone's VPN subnet as an allowed address pair) with a floating IP from
the external network. Credentials come from clouds.yaml / OS_CLOUD through openstack.connect;
ccrp never reads them. Every SDK call goes through the client's api (client.py; retries in
ccrp_cli/retry.py). This class is the servers' lifecycle; it composes the client, the fleet's network
(network.py), its snapshots (images.py) and what the fleet owns (owned.py)."""

from __future__ import annotations

import base64
from collections.abc import Sequence
from pathlib import Path

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...retry import across_zones
from ..base import (GATEWAY, GATEWAY_ROLE, LABEL_ROBOT, LABEL_ROLE, CloneRecord, CloneSpec, CloneState, Origin, OwnedResource, Quota,
                    SnapshotRecord, owner_labels)
from ..cloud import CloudProvider
from . import INFO, errors, images, network, owned
from .client import OpenStackClient

# Nova's server states in ccrp's words.
STATES = {"BUILD": CloneState.PENDING, "REBUILD": CloneState.PENDING, "REBOOT": CloneState.PENDING,
          "HARD_REBOOT": CloneState.PENDING, "RESIZE": CloneState.PENDING, "VERIFY_RESIZE": CloneState.PENDING,
          "MIGRATING": CloneState.PENDING, "ACTIVE": CloneState.RUNNING, "SHUTOFF": CloneState.STOPPED,
          "SUSPENDED": CloneState.STOPPED, "PAUSED": CloneState.STOPPED, "SHELVED": CloneState.STOPPED,
          "SHELVED_OFFLOADED": CloneState.STOPPED, "DELETED": CloneState.DELETING, "SOFT_DELETED": CloneState.DELETING,
          "ERROR": CloneState.ERROR}


class OpenStackProvider(CloudProvider):
    kind = "openstack"
    abilities = INFO.abilities
    images, owned = images, owned  # snapshots and owned resources: CloudProvider hands them the client

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        super().__init__(inv, workdir)
        self.client = OpenStackClient(inv, workdir)
        self.settings = self.client.settings

    def timeout_scale(self, robot: str) -> int:
        """1, as on any cloud, unless CCRP_OPENSTACK_TIMEOUT_SCALE says how many times slower this
        cloud's clones are: a Nova that emulates the CPU (QEMU TCG, as scripts/openstack.sh's
        all-in-one cloud does; docs/openstack.md), which no API tells a project's user."""
        import os

        try:
            return max(1, int(os.environ.get("CCRP_OPENSTACK_TIMEOUT_SCALE", "1")))
        except ValueError:
            return 1

    @staticmethod
    def _build_failed(what: str, tried: list[str], last: BaseException) -> CcrpError | None:
        """Every zone's hosts failed the build: the cloud's fault, not a lack of capacity."""
        if not errors.BUILD_FAILED.search(str(last)):
            return None
        return CcrpError(f"{what}: the cloud could not build it in zones {', '.join(tried)}: {errors.message_of(last)}",
                         hint=errors.BUILD_HINT)

    # -- the fleet's network (network.py) ---------------------------------------------------------
    def bootstrap(self) -> None:
        network.bootstrap(self.client, self.operator_public_key())

    # -- clones ---------------------------------------------------------------------------------
    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Create the clone or reuse what exists of it; roll back only what this attempt created."""
        c = self.client
        payload, _gzipped = INFO.fit_user_data(spec.user_data)  # cloud-init inflates gzip itself
        user_data = base64.b64encode(payload).decode()
        created: list[tuple[str, object]] = []
        what = f"clone of {spec.robot}"
        with c.errors(what):
            try:
                ext, net, subnet, sg = network.fleet_resources(c)
                if spec.role == GATEWAY_ROLE:
                    sg = network.gateway_group(c)
                server = c.server(spec.robot, spec.role)
                origin = Origin.CREATED
                if server is not None:
                    origin = Origin.RESUMED if server.status == "SHUTOFF" else Origin.REUSED  # _revive starts it
                    server = self._revive(server)
                port = self._port(spec, server, net, subnet, sg, created)
                if server is None:
                    server = across_zones(self._zones(spec.robot), lambda z: self._boot(spec, port, user_data, z, created),
                                          classify=c.classify_error, what=f"server for {spec.robot}",
                                          exhausted=self._build_failed)
                # Behind an entry gateway a clone has no floating IP (one it had before the fleet's entry
                # changed is released): its robot comes through the gateway's.
                public = spec.role != "clone" or self.settings.entry != "gateway"
                fip = self._floating_ip(spec, port, ext, created) if public else None
                if not public and origin is not Origin.CREATED:
                    self._release_floating_ips(spec)
            except BaseException as exc:  # Ctrl-C too: what this attempt made must not linger
                left = self._rollback(created)
                if not left or not (isinstance(exc, CcrpError) or errors.is_sdk_error(exc)):
                    raise
                err = exc if isinstance(exc, CcrpError) else errors.to_ccrp(what, self.settings.cloud, exc)
                err.message += f" (rollback left {', '.join(left)}: `ccrp gc` removes them)"
                if err is exc:
                    raise
                raise err from exc
        word = server.status or "BUILD"
        return CloneRecord(robot=spec.robot, provider_id=server.id, state=CloneState.of(word, STATES), status=word,
                           public_ip=fip.floating_ip_address if fip else None, common_ip=port.fixed_ips[0]["ip_address"],
                           origin=origin)

    def _revive(self, server):
        """A reused server must run: start a stopped one; an ERROR one is not ours to replace
        silently (it may hold what the operator wants to look at)."""
        c = self.client
        if server.status == "ERROR":
            fault = (server.fault or {}).get("message") or "no fault reported"
            raise CcrpError(f"server {server.name} is in ERROR ({fault})",
                            hint=f"ccrp clone delete --robot {server.metadata.get(LABEL_ROBOT)} and create it again")
        if server.status == "SHUTOFF":
            c.api("start server", c.compute.start_server, server)
            server = c.api("wait for server", c.compute.wait_for_server, server, status="ACTIVE",
                              failures=["ERROR"], interval=c.poll_interval, wait=c.boot_timeout)
        return server

    def _zones(self, robot: str) -> list[str]:
        pinned = getattr(self.inv.robot(robot), "zone", None)
        return [pinned] if pinned else (self.settings.zones or [""])  # "": Nova picks the zone

    def _port(self, spec: CloneSpec, server, net, subnet, sg, created: list):
        """The clone's port on the common network: its fixed IP, and the clone's VPN subnet as an
        allowed address pair (so other clones route to its robot through it)."""
        c = self.client
        mine = c.tagged("ports", spec.role, spec.robot)
        port = next((p for p in mine if server is not None and p.device_id == server.id), None) or \
            next((p for p in mine if not p.device_id), None)  # left by an attempt that died before the server
        if port is not None:
            return port
        pairs = [{"ip_address": spec.vpn_subnet}] if spec.vpn_subnet else []
        port = c.create_tagged("port", c.network.create_port, c.network.delete_port, c.tags(spec.role, spec.robot),
                                  name=c.server_name(spec.robot, spec.role), network_id=net.id,
                                  fixed_ips=[{"subnet_id": subnet.id, "ip_address": spec.common_ip}],
                                  allowed_address_pairs=pairs, security_group_ids=[sg.id])
        created.append(("port", port))
        return port

    def _boot(self, spec: CloneSpec, port, user_data: str, zone: str, created: list):
        """One server in one zone, until ACTIVE. A server the scheduler could not place goes to
        ERROR: delete it and raise ServerFault so across_zones tries the next zone."""
        c = self.client
        flavor = self._flavor(spec.robot)
        image = c.find_or_fail("image", spec.image, c.image.find_image, errors.IMAGE_HINT)
        extra = {"availability_zone": zone} if zone else {}
        from openstack.exceptions import BadRequestException, ResourceFailure

        try:
            server = c.api("create server", c.compute.create_server, name=c.server_name(spec.robot, spec.role),
                              image_id=image.id, flavor_id=flavor.id, networks=[{"port": port.id}], user_data=user_data,
                              config_drive=True, key_name=c.name(),
                              metadata=owner_labels(self.fleet, spec.role, spec.robot), **extra)
        except BadRequestException as exc:
            # Deleted from Glance after the lookup above: a real Nova answers 400 "Can not find
            # requested image", naming no image (docs/openstack.md, differences).
            if not errors.IMAGE_GONE.search(errors.message_of(exc)):
                raise
            raise CcrpError(f"image {spec.image!r} not found on cloud {self.settings.cloud!r} "
                            f"(Nova: {errors.message_of(exc)})", hint=errors.IMAGE_HINT) from None
        created.append(("instance", server))

        try:
            return c.api("wait for server", c.compute.wait_for_server, server, status="ACTIVE",
                            failures=["ERROR"], interval=c.poll_interval, wait=c.boot_timeout)
        except ResourceFailure:
            failed = c.api("get server", c.compute.get_server, server.id)
            fault = (failed.fault or {}).get("message") or "no fault reported"
            c.delete_server(server)
            created.remove(("instance", server))
            raise errors.ServerFault(f"server {server.name} failed in zone {zone or 'default'}: {fault}") from None

    def _floating_ip(self, spec: CloneSpec, port, ext, created: list):
        c = self.client
        attached = c.listing("floating IPs", c.network.ips, port_id=port.id)
        if attached:
            return attached[0]
        robot = spec.robot
        free = next((f for f in c.tagged("fips", spec.role, robot) if not f.port_id), None)
        if free is not None:  # allocated by an attempt that died before attaching it
            return c.api("attach floating IP", c.network.update_ip, free, port_id=port.id)
        fip = c.create_tagged("floating IP", c.network.create_ip, c.network.delete_ip, c.tags(spec.role, robot),
                                 floating_network_id=ext.id, port_id=port.id,
                                 description=f"ccrp fleet {self.fleet}: clone of {robot}")
        created.append(("floating_ip", fip))
        return fip

    def _release_floating_ips(self, spec: CloneSpec) -> None:
        c = self.client
        for fip in c.tagged("fips", spec.role, spec.robot):
            owned.delete(c, OwnedResource(kind="floating_ip", id=fip.id, name=fip.floating_ip_address or "", robot=spec.robot))

    def _rollback(self, created: list) -> list[str]:
        """Delete what this attempt created, newest first; what could not go is reported."""
        c = self.client
        left = []
        for kind, res in reversed(created):
            try:
                owned.delete(c, OwnedResource(kind=kind, id=res.id, name=res.name or ""), wait=True)
            except Exception:  # noqa: BLE001 - best effort: report, never mask the real failure
                left.append(f"{kind} {res.id}")
        return left

    def _record(self, server) -> CloneRecord:
        public = common = None
        for addrs in (server.addresses or {}).values():
            for a in addrs:
                if a.get("OS-EXT-IPS:type") == "floating":
                    public = a["addr"]
                elif a.get("OS-EXT-IPS:type") == "fixed":
                    common = a["addr"]
        return CloneRecord(robot=server.metadata.get(LABEL_ROBOT, ""), provider_id=server.id,
                           state=CloneState.of(server.status, STATES), status=server.status,
                           public_ip=public, common_ip=common)

    def gateway(self) -> CloneRecord | None:
        """The fleet's entry gateway: the server of role "gateway" (its floating IP is the fleet's
        address: kept, tagged, when the server goes, and attached again to the next one)."""
        c = self.client
        with c.errors("find the entry gateway"):
            server = c.server(GATEWAY, GATEWAY_ROLE)
            return self._record(server) if server is not None else None

    def query(self) -> dict[str, CloneRecord]:
        c = self.client
        with c.errors("list clones"):
            return {r.robot: r for r in (self._record(s) for s in c.servers()
                                         if s.metadata.get(LABEL_ROLE) == "clone")}

    def stop_instance(self, robot: str) -> bool:
        c = self.client
        with c.errors(f"stop clone of {robot}"):
            server = c.server(robot, role="clone")
            if server is None or server.status != "ACTIVE":
                return False
            c.api("stop server", c.compute.stop_server, server)
            return True

    def terminate(self, robot: str) -> bool:
        """The robot's server(s), floating IP and port: owned ones only."""
        c = self.client
        with c.errors(f"delete clone of {robot}"):
            servers = c.servers(robot)
            for server in servers:
                c.delete_server(server)
            for kind, collection in (("floating_ip", "fips"), ("port", "ports")):
                for res in c.tagged(collection, None, robot):
                    owned.delete(c, OwnedResource(kind=kind, id=res.id, name=res.name or "", robot=robot))
            return bool(servers)

    def console_output(self, robot: str) -> str:
        c = self.client
        with c.errors(f"console of {robot}"):
            server = c.running_server(robot)
            out = c.api("console output", c.compute.get_server_console_output, server)
            return (out or {}).get("output") or ""

    # -- doctor ---------------------------------------------------------------------------------
    def check_credentials(self) -> str:
        """Authenticate (a token from Keystone): what `ccrp doctor` reports."""
        c = self.client
        with c.errors(f"cloud {self.settings.cloud}"):
            c.api("authenticate", c.conn.authorize)
            return f"cloud {self.settings.cloud!r}: authenticated, project {c.conn.current_project_id}"

    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]:
        """The project's quotas a clone draws on, with what the clones of `robots` take: Nova's
        compute limits (instances, cores, RAM: limit and usage, /limits) for a server of the robot's
        flavor, and Neutron's floating IPs (limit and usage, /quotas/<project>/details) for its
        public address (none for a robot holding one already; left out where Neutron has no quota
        details). -1 is unlimited: left out."""
        c = self.client
        scope = f"project of cloud {self.settings.cloud!r}"
        hint = "ask the cloud's admin to raise it (`openstack quota show` lists the project's quotas)"
        with c.errors("quotas"):
            a = c.api("compute limits", c.compute.get_limits).absolute
            fips = self._floating_ip_quota()
            held = {t.split("=", 1)[1] for f in (c.tagged("fips", "clone") if robots else [])
                    for t in f.tags if t.startswith(f"{LABEL_ROBOT}=")}
            flavors = {r: self._flavor(r) for r in robots}
            default = self._flavor(None)
            # Behind an entry gateway a clone takes no floating IP; the gateway, while there is none,
            # takes one server of the fleet's flavor and the fleet's one floating IP.
            gateway = self.settings.entry == "gateway"
            making = 1.0 if gateway and robots and c.server(GATEWAY, GATEWAY_ROLE) is None else 0.0
            rows = [("instances", a.instances, a.instances_used, lambda f: 1.0),
                    ("cores", a.total_cores, a.total_cores_used, lambda f: float(f.vcpus)),
                    ("ram (MB)", a.total_ram, a.total_ram_used, lambda f: float(f.ram))]
            found = [Quota(name=name, scope=scope, limit=limit, used=used, per_clone=size(default),
                           per_robot={r: size(f) for r, f in flavors.items() if size(f) != size(default)}, hint=hint,
                           once=making * size(default))
                     for name, limit, used, size in rows if limit is not None and limit >= 0]
            if fips.get("limit") is not None and fips["limit"] >= 0:
                found.append(Quota(name="floating-ips", scope=scope, limit=fips["limit"], used=fips.get("used") or 0,
                                   per_clone=0 if gateway else 1, per_robot={r: 0.0 for r in robots if r in held},
                                   hint=hint, once=making))
            return found

    def _floating_ip_quota(self) -> dict:
        """Neutron's {limit, used, reserved} of floating IPs for the project; {} where the cloud
        has no `quota_details` extension (or does not show them to the project)."""
        c = self.client
        from openstack.exceptions import ForbiddenException, NotFoundException

        project = c.api("authenticate", lambda: c.conn.current_project_id)
        try:
            return c.api("network quota", c.network.get_quota, project, details=True).floating_ips or {}
        except (NotFoundException, ForbiddenException):
            return {}

    def _flavor(self, robot: str | None):
        """The flavor of the robot's server (the fleet's, for None), looked up once per name."""
        c = self.client
        name = getattr(self.inv.robot(robot), "instance_type", None) if robot else None
        name = name or self.settings.flavor
        return c.cached(f"flavor:{name}", lambda: c.find_or_fail("flavor", name, c.compute.find_flavor,
                                                                 "provider.flavor: `openstack flavor list`"))
