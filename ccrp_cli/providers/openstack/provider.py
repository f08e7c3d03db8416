"""OpenStack provider: a clone is a Nova server on the fleet's common network (Neutron port
with a fixed IP and the clone's VPN subnet as an allowed address pair) with a floating IP from
the external network. Credentials come from clouds.yaml / OS_CLOUD through openstack.connect;
ccrp never reads them. Every SDK call goes through self.api (retries in ccrp_cli/retry.py)."""

from __future__ import annotations

import base64
import threading
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import cast

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...retry import across_zones
from ..base import (LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, CloneRecord, CloneSpec, CloneState,
                    Origin, OwnedResource, Quota, ResourceKind, owner_labels)
from ..cloud import CloudProvider
from . import INFO, errors, shared
from .images import Images
from .owned import Owned
from .settings import OpenStackSettings

# Nova's server states in ccrp's words.
STATES = {"BUILD": CloneState.PENDING, "REBUILD": CloneState.PENDING, "REBOOT": CloneState.PENDING,
          "HARD_REBOOT": CloneState.PENDING, "RESIZE": CloneState.PENDING, "VERIFY_RESIZE": CloneState.PENDING,
          "MIGRATING": CloneState.PENDING, "ACTIVE": CloneState.RUNNING, "SHUTOFF": CloneState.STOPPED,
          "SUSPENDED": CloneState.STOPPED, "PAUSED": CloneState.STOPPED, "SHELVED": CloneState.STOPPED,
          "SHELVED_OFFLOADED": CloneState.STOPPED, "DELETED": CloneState.DELETING, "SOFT_DELETED": CloneState.DELETING,
          "ERROR": CloneState.ERROR}


def _connect(cloud: str):
    try:
        import openstack
    except ImportError:
        raise CcrpError("openstacksdk is not installed", hint="pip install 'ccrp[openstack]'") from None
    from openstack.exceptions import ConfigException

    try:
        return openstack.connect(cloud=cloud)
    except ConfigException as exc:
        raise CcrpError(f"cloud {cloud!r} is not configured: {errors.message_of(exc)}",
                        hint="add it to clouds.yaml (or set OS_CLOUD / OS_CLIENT_CONFIG_FILE)") from None


class OpenStackProvider(Images, Owned, CloudProvider):
    kind = "openstack"
    abilities = INFO.abilities
    poll_interval = 2.0  # seconds between status checks of a booting server / saving image
    boot_timeout = 900
    image_timeout = 1800

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        super().__init__(inv, workdir)
        self.settings = cast(OpenStackSettings, inv.provider)  # get_provider picked this backend by these settings' kind
        self.conn = _connect(self.settings.cloud)
        self._lock = threading.Lock()
        self._cache: dict[str, object] = {}  # shared lookups (network, flavor...) for parallel clones

    # -- services: the first use discovers versions over HTTP, so it is an API call too ---------
    @property
    def compute(self):
        return self.api("compute service discovery", getattr, self.conn, "compute")

    @property
    def network(self):
        return self.api("network service discovery", getattr, self.conn, "network")

    @property
    def image(self):
        return self.api("image service discovery", getattr, self.conn, "image")

    # -- names, tags, listings ------------------------------------------------------------------
    def name(self, *parts: str) -> str:
        return "-".join(("ccrp", self.fleet, *parts))

    def server_name(self, robot: str, role: str = "clone") -> str:
        return self.name("cri" if role == "clone" else role, robot)

    def tags(self, role: str, robot: str | None = None) -> list[str]:
        return [f"{k}={v}" for k, v in owner_labels(self.fleet, role, robot).items()]

    def create_tagged(self, what: str, fn, delete, tags: list[str], **attrs):
        """A Neutron resource created with ccrp's ownership tags. Neutron takes `tags` in the POST
        body only with its `tag-creation` extension (2023.1 on). Zed's (scripts/openstack.sh's cloud)
        answers 400 "Attribute 'tags' not allowed in POST" for networks, subnets, routers, security
        groups and floating IPs, and for a port accepts the POST and drops the tags (201, `tags: []`).
        Either way the resource is tagged at once (PUT .../tags, the `standard-attr-tag` extension);
        one that could not be tagged is deleted again, since no listing by tag would ever find it."""
        from openstack.exceptions import BadRequestException

        if not self._cache.get("no-tag-creation"):
            def post():
                try:
                    return fn(tags=tags, **attrs)
                except BadRequestException as exc:
                    if "'tags' not allowed in POST" not in str(exc):
                        raise
                    return None
            res = self.api(f"create {what}", post)
            if res is not None and set(tags) <= set(getattr(res, "tags", None) or []):
                return res
            if res is None:
                with self._lock:
                    self._cache["no-tag-creation"] = True
        else:
            res = None
        if res is None:
            res = self.api(f"create {what}", fn, **attrs)
        try:
            self.api(f"tag {what}", self.network.set_tags, res, tags)
        except BaseException:
            try:
                self.api(f"delete untagged {what}", delete, res, ignore_missing=True)
            except Exception:  # noqa: BLE001 - the tagging failure is the one to report
                pass
            raise
        return res

    def timeout_scale(self, robot: str) -> int:
        """1, as on any cloud, unless CCRP_OPENSTACK_TIMEOUT_SCALE says how many times slower this
        cloud's clones are: a Nova that emulates the CPU (QEMU TCG, as scripts/openstack.sh's
        all-in-one cloud does; docs/openstack.md), which no API tells a project's user."""
        import os

        try:
            return max(1, int(os.environ.get("CCRP_OPENSTACK_TIMEOUT_SCALE", "1")))
        except ValueError:
            return 1

    def classify_error(self, exc: BaseException):
        return errors.classify(exc)

    @staticmethod
    def _build_failed(what: str, tried: list[str], last: BaseException) -> CcrpError | None:
        """Every zone's hosts failed the build: the cloud's fault, not a lack of capacity."""
        if not errors.BUILD_FAILED.search(str(last)):
            return None
        return CcrpError(f"{what}: the cloud could not build it in zones {', '.join(tried)}: {errors.message_of(last)}",
                         hint=errors.BUILD_HINT)

    def listing(self, what: str, fn, **query) -> list:
        """A list call (the SDK returns a lazy generator: the requests happen inside api())."""
        return self.api(f"list {what}", lambda: list(fn(**query)))

    def owned(self, collection: str, role: str | None = None, robot: str | None = None) -> list:
        """Neutron resources carrying this fleet's tags (all of them must match)."""
        tags = [f"{LABEL_MANAGED}=true", f"{LABEL_FLEET}={self.fleet}"]
        tags += [f"{LABEL_ROLE}={role}"] if role else []
        tags += [f"{LABEL_ROBOT}={robot}"] if robot else []
        method = "ips" if collection == "fips" else collection
        return self.listing(collection, getattr(self.network, method), tags=",".join(tags))

    def _is_owned(self, labels: dict | None, robot: str | None = None) -> bool:
        labels = labels or {}
        return (labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == self.fleet
                and (robot is None or labels.get(LABEL_ROBOT) == robot))

    def servers(self, robot: str | None = None) -> list:
        """This fleet's servers: Nova has no idempotency token, so name AND metadata identify them."""
        pattern = f"^{self.name()}-"
        found = self.listing("servers", self.compute.servers, name=pattern)
        return [s for s in found if s.name.startswith(pattern[1:]) and self._is_owned(s.metadata, robot)]

    def _server(self, robot: str, role: str | None = None):
        found = [s for s in self.servers(robot) if role is None or s.metadata.get(LABEL_ROLE) == role]
        if len(found) > 1:
            raise CcrpError(f"robot {robot!r} has {len(found)} servers on cloud {self.settings.cloud!r}",
                            hint=f"delete the extra ones: `ccrp clone delete --robot {robot}` then recreate")
        return found[0] if found else None

    def _running_server(self, robot: str):
        server = self._server(robot)
        if server is None:
            raise CcrpError(f"robot {robot!r} has no clone on cloud {self.settings.cloud!r}",
                            hint=f"ccrp clone create --robot {robot}")
        return server

    def _cached(self, key: str, make):
        with self._lock:
            if key not in self._cache:
                self._cache[key] = make()
            return self._cache[key]

    @contextmanager
    def _errors(self, what: str):
        """SDK failures leave a public method as one-line CcrpErrors with a hint."""
        try:
            yield
        except CcrpError:
            raise
        except Exception as exc:
            if not errors.is_sdk_error(exc):
                raise
            raise errors.to_ccrp(what, self.settings.cloud, exc) from exc

    # -- bootstrap ------------------------------------------------------------------------------
    def bootstrap(self) -> None:
        with self._errors(f"bootstrap of fleet {self.fleet}"):
            ext = shared.external_network(self)
            net, subnet = shared.common_network(self, create=True)
            if not self.settings.network:  # a named network is the operator's, already routed
                shared.router(self, subnet, ext)
            sg = shared.security_group(self)
            shared.key_pair(self)
            with self._lock:
                self._cache.update(ext=ext, net=(net, subnet), sg=sg)

    def _fleet_resources(self):
        ext = self._cached("ext", lambda: shared.external_network(self))
        net, subnet = self._cached("net", lambda: shared.common_network(self, create=False))
        sg = self._cached("sg", lambda: next(iter(self.owned("security_groups", "network")), None))
        if sg is None:
            raise CcrpError(f"fleet {self.fleet!r} has no security group yet", hint="run `ccrp fleet up`")
        return ext, net, subnet, sg

    # -- clones ---------------------------------------------------------------------------------
    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Create the clone or reuse what exists of it; roll back only what this attempt created."""
        payload, _gzipped = INFO.fit_user_data(spec.user_data)  # cloud-init inflates gzip itself
        user_data = base64.b64encode(payload).decode()
        created: list[tuple[str, object]] = []
        what = f"clone of {spec.robot}"
        with self._errors(what):
            try:
                ext, net, subnet, sg = self._fleet_resources()
                server = self._server(spec.robot, spec.role)
                origin = Origin.CREATED
                if server is not None:
                    origin = Origin.RESUMED if server.status == "SHUTOFF" else Origin.REUSED  # _revive starts it
                    server = self._revive(server)
                port = self._port(spec, server, net, subnet, sg, created)
                if server is None:
                    server = across_zones(self._zones(spec.robot), lambda z: self._boot(spec, port, user_data, z, created),
                                          classify=self.classify_error, what=f"server for {spec.robot}",
                                          exhausted=self._build_failed)
                fip = self._floating_ip(spec, port, ext, created)
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
                           public_ip=fip.floating_ip_address, common_ip=port.fixed_ips[0]["ip_address"], origin=origin)

    def _revive(self, server):
        """A reused server must run: start a stopped one; an ERROR one is not ours to replace
        silently (it may hold what the operator wants to look at)."""
        if server.status == "ERROR":
            fault = (server.fault or {}).get("message") or "no fault reported"
            raise CcrpError(f"server {server.name} is in ERROR ({fault})",
                            hint=f"ccrp clone delete --robot {server.metadata.get(LABEL_ROBOT)} and create it again")
        if server.status == "SHUTOFF":
            self.api("start server", self.compute.start_server, server)
            server = self.api("wait for server", self.compute.wait_for_server, server, status="ACTIVE",
                              failures=["ERROR"], interval=self.poll_interval, wait=self.boot_timeout)
        return server

    def _zones(self, robot: str) -> list[str]:
        pinned = getattr(self.inv.robot(robot), "zone", None)
        return [pinned] if pinned else (self.settings.zones or [""])  # "": Nova picks the zone

    def _port(self, spec: CloneSpec, server, net, subnet, sg, created: list):
        """The clone's port on the common network: its fixed IP, and the clone's VPN subnet as an
        allowed address pair (so other clones route to its robot through it)."""
        mine = self.owned("ports", spec.role, spec.robot)
        port = next((p for p in mine if server is not None and p.device_id == server.id), None) or \
            next((p for p in mine if not p.device_id), None)  # left by an attempt that died before the server
        if port is not None:
            return port
        pairs = [{"ip_address": spec.vpn_subnet}] if spec.vpn_subnet else []
        port = self.create_tagged("port", self.network.create_port, self.network.delete_port, self.tags(spec.role, spec.robot),
                                  name=self.server_name(spec.robot, spec.role), network_id=net.id,
                                  fixed_ips=[{"subnet_id": subnet.id, "ip_address": spec.common_ip}],
                                  allowed_address_pairs=pairs, security_group_ids=[sg.id])
        created.append(("port", port))
        return port

    def _boot(self, spec: CloneSpec, port, user_data: str, zone: str, created: list):
        """One server in one zone, until ACTIVE. A server the scheduler could not place goes to
        ERROR: delete it and raise ServerFault so across_zones tries the next zone."""
        flavor = self._flavor(spec.robot)
        image = self._find("image", spec.image, self.image.find_image, errors.IMAGE_HINT)
        extra = {"availability_zone": zone} if zone else {}
        from openstack.exceptions import BadRequestException, ResourceFailure

        try:
            server = self.api("create server", self.compute.create_server, name=self.server_name(spec.robot, spec.role),
                              image_id=image.id, flavor_id=flavor.id, networks=[{"port": port.id}], user_data=user_data,
                              config_drive=True, key_name=self.name(),
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
            return self.api("wait for server", self.compute.wait_for_server, server, status="ACTIVE",
                            failures=["ERROR"], interval=self.poll_interval, wait=self.boot_timeout)
        except ResourceFailure:
            failed = self.api("get server", self.compute.get_server, server.id)
            fault = (failed.fault or {}).get("message") or "no fault reported"
            self._delete_server(server)
            created.remove(("instance", server))
            raise errors.ServerFault(f"server {server.name} failed in zone {zone or 'default'}: {fault}") from None

    def find(self, what: str, fn, name_or_id: str):
        """A find_* call; None when the cloud has no such resource."""
        from openstack.exceptions import NotFoundException

        try:
            return self.api(f"find {what}", fn, name_or_id, ignore_missing=False)
        except NotFoundException:
            return None

    def _find(self, what: str, name_or_id: str, fn, hint: str):
        found = self.find(what, fn, name_or_id)
        if found is None:
            raise CcrpError(f"{what} {name_or_id!r} not found on cloud {self.settings.cloud!r}", hint=hint)
        return found

    def _floating_ip(self, spec: CloneSpec, port, ext, created: list):
        attached = self.listing("floating IPs", self.network.ips, port_id=port.id)
        if attached:
            return attached[0]
        robot = spec.robot
        free = next((f for f in self.owned("fips", spec.role, robot) if not f.port_id), None)
        if free is not None:  # allocated by an attempt that died before attaching it
            return self.api("attach floating IP", self.network.update_ip, free, port_id=port.id)
        fip = self.create_tagged("floating IP", self.network.create_ip, self.network.delete_ip, self.tags(spec.role, robot),
                                 floating_network_id=ext.id, port_id=port.id,
                                 description=f"ccrp fleet {self.fleet}: clone of {robot}")
        created.append(("floating_ip", fip))
        return fip

    def _rollback(self, created: list) -> list[str]:
        """Delete what this attempt created, newest first; what could not go is reported."""
        left = []
        for kind, res in reversed(created):
            try:
                self._delete(OwnedResource(kind=kind, id=res.id, name=res.name or ""), wait=True)
            except Exception:  # noqa: BLE001 - best effort: report, never mask the real failure
                left.append(f"{kind} {res.id}")
        return left

    def _delete_server(self, server) -> None:
        """Delete a server (a Server or an id) and wait until Nova has let go of its port."""
        from openstack.compute.v2.server import Server

        server_id = getattr(server, "id", server)
        self.api("delete server", self.compute.delete_server, server_id, ignore_missing=True)
        self.api("wait for deletion", self.compute.wait_for_delete, Server(id=server_id),
                 interval=self.poll_interval, wait=self.boot_timeout)

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

    def query(self) -> dict[str, CloneRecord]:
        with self._errors("list clones"):
            return {r.robot: r for r in (self._record(s) for s in self.servers()
                                         if s.metadata.get(LABEL_ROLE) == "clone")}

    def stop_instance(self, robot: str) -> bool:
        with self._errors(f"stop clone of {robot}"):
            server = self._server(robot, role="clone")
            if server is None or server.status != "ACTIVE":
                return False
            self.api("stop server", self.compute.stop_server, server)
            return True

    def terminate(self, robot: str) -> bool:
        """The robot's server(s), floating IP and port: owned ones only."""
        with self._errors(f"delete clone of {robot}"):
            servers = self.servers(robot)
            for server in servers:
                self._delete_server(server)
            kinds: tuple[tuple[ResourceKind, str], ...] = (("floating_ip", "fips"), ("port", "ports"))
            for kind, collection in kinds:
                for res in self.owned(collection, None, robot):
                    self._delete(OwnedResource(kind=kind, id=res.id, name=res.name or "", robot=robot))
            return bool(servers)

    def console_output(self, robot: str) -> str:
        with self._errors(f"console of {robot}"):
            server = self._running_server(robot)
            out = self.api("console output", self.compute.get_server_console_output, server)
            return (out or {}).get("output") or ""

    # -- doctor ---------------------------------------------------------------------------------
    def check_credentials(self) -> str:
        """Authenticate (a token from Keystone): what `ccrp doctor` reports."""
        with self._errors(f"cloud {self.settings.cloud}"):
            self.api("authenticate", self.conn.authorize)
            return f"cloud {self.settings.cloud!r}: authenticated, project {self.conn.current_project_id}"

    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]:
        """The project's quotas a clone draws on, with what the clones of `robots` take: Nova's
        compute limits (instances, cores, RAM: limit and usage, /limits) for a server of the robot's
        flavor, and Neutron's floating IPs (limit and usage, /quotas/<project>/details) for its
        public address (none for a robot holding one already; left out where Neutron has no quota
        details). -1 is unlimited: left out."""
        scope = f"project of cloud {self.settings.cloud!r}"
        hint = "ask the cloud's admin to raise it (`openstack quota show` lists the project's quotas)"
        with self._errors("quotas"):
            a = self.api("compute limits", self.compute.get_limits).absolute
            fips = self._floating_ip_quota()
            held = {t.split("=", 1)[1] for f in (self.owned("fips", "clone") if robots else [])
                    for t in f.tags if t.startswith(f"{LABEL_ROBOT}=")}
            flavors = {r: self._flavor(r) for r in robots}
            default = self._flavor(None)
            rows = [("instances", a.instances, a.instances_used, lambda f: 1.0),
                    ("cores", a.total_cores, a.total_cores_used, lambda f: float(f.vcpus)),
                    ("ram (MB)", a.total_ram, a.total_ram_used, lambda f: float(f.ram))]
            found = [Quota(name=name, scope=scope, limit=limit, used=used, per_clone=size(default),
                           per_robot={r: size(f) for r, f in flavors.items() if size(f) != size(default)}, hint=hint)
                     for name, limit, used, size in rows if limit is not None and limit >= 0]
            if fips.get("limit") is not None and fips["limit"] >= 0:
                found.append(Quota(name="floating-ips", scope=scope, limit=fips["limit"], used=fips.get("used") or 0,
                                   per_clone=1, per_robot={r: 0.0 for r in robots if r in held}, hint=hint))
            return found

    def _floating_ip_quota(self) -> dict:
        """Neutron's {limit, used, reserved} of floating IPs for the project; {} where the cloud
        has no `quota_details` extension (or does not show them to the project)."""
        from openstack.exceptions import ForbiddenException, NotFoundException

        project = self.api("authenticate", lambda: self.conn.current_project_id)
        try:
            return self.api("network quota", self.network.get_quota, project, details=True).floating_ips or {}
        except (NotFoundException, ForbiddenException):
            return {}

    def _flavor(self, robot: str | None):
        """The flavor of the robot's server (the fleet's, for None), looked up once per name."""
        name = getattr(self.inv.robot(robot), "instance_type", None) if robot else None
        name = name or self.settings.flavor
        return self._cached(f"flavor:{name}", lambda: self._find("flavor", name, self.compute.find_flavor,
                                                                 "provider.flavor: `openstack flavor list`"))
