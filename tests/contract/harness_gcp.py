"""GCP harness: autospecced compute_v1 clients over an in-memory fake project.

Each client is `create_autospec(compute_v1.<X>Client, instance=True)`, so a call with a wrong
method name or argument fails as it would against the SDK. Their side effects act on FakeProject
and answer with the SDK's own types: compute_v1 messages, ExtendedOperation futures (done, with
GCE's http_error_* fields on failure), and the SDK's pagers (lists come in pages of PAGE items).
The fake enforces what GCE enforces and ccrp relies on: unique names per zone, request-id
replay, IPs inside the subnetwork, label syntax, the 256 KiB metadata value limit, no delete of
a network still in use, a regional CPU quota, zones that can run out of capacity, routes' fields
(a CIDR destination, a priority of 0-65535, valid tags, a next-hop instance that exists and forwards). External IPs
are GCE's: an access config without natIP gets an ephemeral IP, released when the instance stops
and replaced by another at its next start; one with natIP must name a RESERVED address of the
region, which then is IN_USE by the instance and keeps its IP across stop/start; an address in
use cannot be released; an ephemeral IP can be promoted (addresses.insert with its IP); reserved
addresses count against a regional STATIC_ADDRESSES quota, external IPs held by instances against
IN_USE_ADDRESSES (both 8 by default, as in a new project); regions.get reports each quota's limit
and its usage counted from what exists.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import importlib
import ipaddress
import random
import re
import threading
import time
from collections import Counter
from pathlib import Path
from unittest import mock

from google.api_core import exceptions
from google.api_core.extended_operation import ExtendedOperation
from google.cloud import compute_v1 as c

from ccrp_cli.models.inventory import Inventory
from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, CloneSpec, owner_labels
from ccrp_cli.providers.gcp.provider import GcpProvider
from ccrp_cli.providers.gcp.client import Clients
from ccrp_cli.providers.gcp.ownership import description_marks, tail

from . import specs
from .harness import FLEET

PROJECT, REGION = "ccrp-test", "europe-west2"
ZONES = [f"{REGION}-a", f"{REGION}-b", f"{REGION}-c"]
BASE = "https://www.googleapis.com/compute/v1/"
PUBLIC_IMAGE = "projects/debian-cloud/global/images/debian-12-bookworm-v20240312"
PAGE = 3
NAME = re.compile(r"^[a-z]([-a-z0-9]{0,61}[a-z0-9])?$")
LABEL = re.compile(r"^[a-z0-9_-]{0,63}$")
METADATA_VALUE_MAX = 256 * 1024
VCPUS = {"e2-micro": 2, "e2-small": 2, "e2-medium": 2, "e2-standard-4": 4}


class FakeOperation(ExtendedOperation):
    """What compute_v1 clients return: GCE names its error fields http_error_*."""

    @property
    def error_code(self):
        return self._extended_operation.http_error_status_code

    @property
    def error_message(self):
        return self._extended_operation.http_error_message


def quota_exceeded(metric: str, limit: float) -> str:
    """GCE's text for a request over a regional quota (the limit as GCE prints it: 8.0)."""
    return f"Quota '{metric}' exceeded.  Limit: {float(limit)} in region {REGION}."


def inventory(zones: list[str] | None = None, **provider) -> Inventory:
    """A GCP inventory; per clone unless `entry` says otherwise (the contract proves a clone's own
    public address; the gateway's layout has its tests in tests/unit/test_gcp_provider.py)."""
    return specs.inventory({"kind": "gcp", "project": PROJECT, "region": REGION, "zones": zones or ZONES[:2],
                            "operator_cidr": specs.OPERATOR_CIDR, "entry": "per-clone", **provider})


def _copy(message):
    return type(message)(message)


def _request(cls, request, kwargs):
    """The request message a client method would build from request= or flattened fields."""
    if request is not None:
        return cls(request)
    return cls(**{k: v for k, v in kwargs.items() if k not in ("retry", "timeout", "metadata")})


def _label_filter(text: str) -> dict[str, str]:
    """GCE list filter `(labels.k = "v") AND ...`; anything else is a 400, as GCE would answer."""
    clauses = re.findall(r'\(labels\.([a-z0-9_-]+) = "([a-z0-9_-]*)"\)', text or "")
    if re.sub(r'\(labels\.[a-z0-9_-]+ = "[a-z0-9_-]*"\)|AND|\s', "", text or ""):
        raise exceptions.BadRequest(f"Invalid list filter expression '{text}'.", errors=[{"reason": "invalid"}])
    return dict(clauses)


def _not_found(link: str):
    return exceptions.NotFound(f"The resource '{link}' was not found", errors=[{"reason": "notFound"}])


class FakeProject:
    """One GCE project with one region, driven through autospecced compute_v1 clients."""

    def __init__(self, cpu_quota: float = 24, address_quota: int = 8, in_use_address_quota: int = 8) -> None:
        self.lock = threading.RLock()
        self.rng = random.Random(7)
        self.instances: dict[tuple[str, str], c.Instance] = {}
        self.networks: dict[str, c.Network] = {}
        self.subnetworks: dict[str, c.Subnetwork] = {}
        self.firewalls: dict[str, c.Firewall] = {}
        self.routes: dict[str, c.Route] = {}
        self.images: dict[str, c.Image] = {}
        self.addresses: dict[str, c.Address] = {}  # reserved external addresses of REGION
        self.address_quota = address_quota  # STATIC_ADDRESSES: reserved addresses
        self.in_use_address_quota = in_use_address_quota  # IN_USE_ADDRESSES: external IPs instances hold
        self._external = 0  # where the next external IP is looked for
        self.replies: dict[str, c.Operation] = {}  # requestId -> the operation GCE answered with
        self.calls: Counter = Counter()
        self.throttled = 0.0
        self._debt, self._refusals = 0.0, 0
        self.latency = 0.0
        self.cpu_quota = cpu_quota
        self.exhausted: set[str] = set()  # zones without capacity
        self.fail_route_for: set[str] = set()  # robots whose next route insert fails
        self.serial: dict[str, str] = {}
        self._ops = 0
        self.clients = self._clients()

    # -- plumbing -------------------------------------------------------------------------------
    def _clients(self) -> Clients:
        handlers = {
            "instances": ("InstancesClient", ["insert", "get", "delete", "start", "stop", "aggregated_list",
                                              "get_serial_port_output", "add_access_config",
                                              "delete_access_config"]),
            "networks": ("NetworksClient", ["insert", "get", "delete", "list"]),
            "subnetworks": ("SubnetworksClient", ["insert", "get", "delete", "list"]),
            "firewalls": ("FirewallsClient", ["insert", "get", "update", "delete", "list"]),
            "routes": ("RoutesClient", ["insert", "get", "delete", "list"]),
            "addresses": ("AddressesClient", ["insert", "get", "delete", "list"]),
            "images": ("ImagesClient", ["insert", "get", "delete", "list"]),
            "regions": ("RegionsClient", ["get"]),
            "machine_types": ("MachineTypesClient", ["get"]),
        }
        built = {}
        for service, (cls, methods) in handlers.items():
            client = mock.create_autospec(getattr(c, cls), instance=True)
            for method in methods:
                getattr(client, method).side_effect = self._endpoint(
                    f"{service}.{method}", getattr(self, f"_{service}_{method}"))
            built[service] = client
        return Clients(**built)

    def _endpoint(self, name: str, handler):
        def call(*args, **kwargs):
            with self.lock:
                self.calls[name] += 1
                # Exactly `throttled` of all calls fail, spread evenly (not at random): a random
                # draw fails one call 8 times running (retry.call's limit) in ~1 of 150 storms.
                self._debt += self.throttled
                throttled = self._debt >= 1
                if throttled:
                    self._debt -= 1
                    self._refusals += 1
            if self.latency:
                time.sleep(self.latency)
            if throttled:
                if self._refusals % 2:
                    raise exceptions.TooManyRequests("Rate Limit Exceeded", errors=[{"reason": "rateLimitExceeded"}])
                raise exceptions.ServiceUnavailable("Backend Error", errors=[{"reason": "backendError"}])
            with self.lock:
                return handler(*args, **kwargs)

        return call

    def _new_id(self) -> int:
        return self.rng.randrange(10**18, 2**63)

    def _operation(self, target: str, kind: str, request_id: str = "", code: int = 0, error: str = "",
                   message: str = "") -> FakeOperation:
        if request_id and request_id in self.replies:
            done = self.replies[request_id]
        else:
            self._ops += 1
            done = c.Operation(name=f"operation-{self._ops}", operation_type=kind, target_link=target,
                               status=c.Operation.Status.DONE)
            if code:
                done.http_error_status_code = code
                done.http_error_message = message
                done.error = c.Error(errors=[c.Errors(code=error, message=message)])
            if request_id:
                self.replies[request_id] = done
        return FakeOperation.make(lambda retry=None: done, lambda: None, done)

    def _replay(self, request_id: str):
        """GCE answers a repeated requestId with the first operation and does nothing else."""
        return self._operation("", "", request_id) if request_id in self.replies else None

    def _pager(self, service: str, pager: str, response_cls, items_of, request):
        """The SDK's own pager over our items, PAGE per page; every page is one API call."""
        module = importlib.import_module(f"google.cloud.compute_v1.services.{service}.pagers")
        aggregated = pager == "AggregatedListPager"

        def page(req, **_kw):
            items = items_of(req)
            start = int(req.page_token or 0)
            chunk = items[start:start + PAGE]
            token = str(start + PAGE) if start + PAGE < len(items) else ""
            # Aggregated lists map scope -> scoped list; plain lists are lists.
            return response_cls(items=dict(chunk) if aggregated else chunk, next_page_token=token)

        return getattr(module, pager)(method=self._endpoint(f"{service}.list_page", page), request=request,
                                      response=page(request))

    def _link(self, path: str) -> str:
        return f"{BASE}projects/{PROJECT}/{path}"

    def _check_zone(self, zone: str) -> None:
        if zone not in ZONES:
            raise _not_found(self._link(f"zones/{zone}"))

    # -- external IPs ---------------------------------------------------------------------------
    def _external_pool(self) -> list[str]:
        return [f"192.0.2.{n}" for n in range(2, 255)]  # TEST-NET-1, never contacted

    def _external_in_use(self) -> set[str]:
        return ({a.nat_i_p for i in self.instances.values() for nic in i.network_interfaces
                 for a in nic.access_configs if a.nat_i_p} | {a.address for a in self.addresses.values()})

    def _free_external_ip(self) -> str:
        """An external IP nobody holds; taken round the pool, so a released IP is not the next one
        given (a restarted instance gets another IP, as on GCE)."""
        pool, used = self._external_pool(), self._external_in_use()
        for _ in range(len(pool)):
            ip = pool[self._external % len(pool)]
            self._external += 1
            if ip not in used:
                return ip
        raise exceptions.Forbidden("Quota 'IN_USE_ADDRESSES' exceeded.", errors=[{"reason": "quotaExceeded"}])

    def _reserved(self, ip: str) -> c.Address | None:
        return next((a for a in self.addresses.values() if ip and a.address == ip), None)

    def _sync_addresses(self) -> None:
        """An address is IN_USE by the instance whose access config holds its IP, else RESERVED
        (an instance that vanished, e.g. deleted by hand, frees it, as on GCE)."""
        holders = {a.nat_i_p: i.self_link for i in self.instances.values() for nic in i.network_interfaces
                   for a in nic.access_configs if a.nat_i_p}
        for address in self.addresses.values():
            user = holders.get(address.address)
            address.status, address.users = ("IN_USE", [user]) if user else ("RESERVED", [])

    def _check_nat(self, access: c.AccessConfig) -> None:
        """An access config naming a natIP may only use a reserved address nobody else uses."""
        if not access.nat_i_p:
            return
        self._sync_addresses()
        address = self._reserved(access.nat_i_p)
        if address is None:
            raise exceptions.BadRequest(f"The specified external IP address '{access.nat_i_p}' was not found in "
                                        f"region '{REGION}'.", errors=[{"reason": "invalid"}])
        if address.status != "RESERVED":
            raise exceptions.BadRequest(f"External IP address: {access.nat_i_p} is already in-use.",
                                        errors=[{"reason": "invalid"}])

    def _take_nat(self, inst: c.Instance, access: c.AccessConfig) -> None:
        """The access config's IP once the instance has it: its reserved address (IN_USE from now
        on), or without natIP an ephemeral one."""
        if self._reserved(access.nat_i_p) is None:
            access.nat_i_p = self._free_external_ip()

    def _stop_nat(self, inst: c.Instance) -> None:
        """At stop GCE releases ephemeral IPs; a reserved address stays on the access config."""
        for nic in inst.network_interfaces:
            for access in nic.access_configs:
                if self._reserved(access.nat_i_p) is None:
                    access.nat_i_p = ""

    def _start_nat(self, inst: c.Instance) -> None:
        for nic in inst.network_interfaces:
            for access in nic.access_configs:
                if not access.nat_i_p:
                    access.nat_i_p = self._free_external_ip()

    # -- instances ------------------------------------------------------------------------------
    def _instance(self, zone: str, name: str) -> c.Instance:
        inst = self.instances.get((zone, name))
        if inst is None:
            raise _not_found(self._link(f"zones/{zone}/instances/{name}"))
        return inst

    def store_instance(self, zone: str, inst: c.Instance) -> c.Instance:
        inst.id = self._new_id()
        inst.zone = self._link(f"zones/{zone}")
        inst.self_link = self._link(f"zones/{zone}/instances/{inst.name}")
        inst.status = "RUNNING"
        inst.creation_timestamp = dt.datetime.now(dt.timezone.utc).isoformat()
        self.instances[(zone, inst.name)] = inst
        return inst

    def _vcpus(self) -> int:
        """The CPUS quota's usage: the vCPUs of every instance but the stopped (TERMINATED) ones."""
        return sum(VCPUS.get(tail(i.machine_type), 2) for i in self.instances.values() if i.status != "TERMINATED")

    def _in_use_addresses(self) -> int:
        """The IN_USE_ADDRESSES quota's usage: external IPs held by instances, ephemeral or reserved."""
        return sum(1 for i in self.instances.values() for nic in i.network_interfaces for a in nic.access_configs
                   if a.nat_i_p)

    def _instances_insert(self, request=None, **kw):
        req = _request(c.InsertInstanceRequest, request, kw)
        if replay := self._replay(req.request_id):
            return replay
        self._check_zone(req.zone)
        inst = _copy(req.instance_resource)
        link = self._link(f"zones/{req.zone}/instances/{inst.name}")
        if not NAME.match(inst.name):
            raise exceptions.BadRequest(f"Invalid value for field 'resource.name': '{inst.name}'.")
        for key, value in inst.labels.items():
            if not (LABEL.match(key) and key and LABEL.match(value)):
                raise exceptions.BadRequest(f"Invalid value for field 'resource.labels': '{key}={value}'.")
        for item in inst.metadata.items:
            if len(item.value.encode()) > METADATA_VALUE_MAX:
                raise exceptions.BadRequest(f"Metadata value for key '{item.key}' is over 256 KiB.")
        if (req.zone, inst.name) in self.instances:
            raise exceptions.Conflict(f"The resource '{link}' already exists", errors=[{"reason": "alreadyExists"}])
        if req.source_machine_image:
            raise _not_found(req.source_machine_image)  # the fake has no machine images
        boot = [d for d in inst.disks if d.boot]
        if len(boot) != 1 or self._image_for(boot[0].initialize_params.source_image) is None:
            raise exceptions.BadRequest("Invalid value for field 'resource.disks': a boot disk from an existing image is required.")
        if len(inst.network_interfaces) != 1:
            raise exceptions.BadRequest("Invalid value for field 'resource.networkInterfaces'.")
        nic = inst.network_interfaces[0]
        subnet = self.subnetworks.get(tail(nic.subnetwork))
        if subnet is None:
            raise _not_found(nic.subnetwork)
        taken = {i.network_interfaces[0].network_i_p for i in self.instances.values() if i.network_interfaces}
        if ipaddress.ip_address(nic.network_i_p) not in ipaddress.ip_network(subnet.ip_cidr_range) or nic.network_i_p in taken:
            raise exceptions.BadRequest(f"IP address '{nic.network_i_p}' is not available in subnetwork {subnet.name}.")
        for access in nic.access_configs:
            self._check_nat(access)
        # Accepted: from here on failures are operation errors, as GCE reports them.
        if self._vcpus() + VCPUS.get(tail(inst.machine_type), 2) > self.cpu_quota:
            return self._operation(link, "insert", req.request_id, 403, "QUOTA_EXCEEDED",
                                   quota_exceeded("CPUS", self.cpu_quota))
        if self._in_use_addresses() + len(nic.access_configs) > self.in_use_address_quota:
            return self._operation(link, "insert", req.request_id, 403, "QUOTA_EXCEEDED",
                                   quota_exceeded("IN_USE_ADDRESSES", self.in_use_address_quota))
        if req.zone in self.exhausted:
            return self._operation(link, "insert", req.request_id, 503, "ZONE_RESOURCE_POOL_EXHAUSTED",
                                   f"The zone 'projects/{PROJECT}/zones/{req.zone}' does not have enough resources "
                                   "available to fulfill the request.  Try a different zone, or try again later.")
        nic.network = subnet.network
        nic.name = "nic0"
        inst.machine_type = self._link(inst.machine_type)
        boot[0].source = self._link(f"zones/{req.zone}/disks/{inst.name}")
        boot[0].initialize_params = c.AttachedDiskInitializeParams()  # GCE does not echo these
        self.store_instance(req.zone, inst)
        for access in nic.access_configs:
            self._take_nat(inst, access)
        self.serial[inst.name] = f"cloud-init: booting {inst.name}\n"
        return self._operation(link, "insert", req.request_id)

    def _image_for(self, source: str):
        if source == PUBLIC_IMAGE:
            return c.Image(name=tail(source))
        return self.images.get(tail(source)) if f"projects/{PROJECT}/global/images/" in source else None

    def _instances_get(self, request=None, **kw):
        req = _request(c.GetInstanceRequest, request, kw)
        return _copy(self._instance(req.zone, req.instance))

    def _instances_start(self, request=None, **kw):
        req = _request(c.StartInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        if inst.status == "TERMINATED":
            self._start_nat(inst)
        inst.status = "RUNNING"
        return self._operation(inst.self_link, "start", req.request_id)

    def _instances_stop(self, request=None, **kw):
        req = _request(c.StopInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        inst.status = "TERMINATED"  # GCE's word for stopped
        self._stop_nat(inst)
        return self._operation(inst.self_link, "stop", req.request_id)

    def _instances_delete(self, request=None, **kw):
        req = _request(c.DeleteInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        del self.instances[(req.zone, req.instance)]  # routes through it stay, as on GCE
        return self._operation(inst.self_link, "delete", req.request_id)

    def _nic(self, inst: c.Instance, name: str) -> c.NetworkInterface:
        nic = next((n for n in inst.network_interfaces if n.name == name), None)
        if nic is None:
            raise exceptions.BadRequest(f"Invalid value for field 'networkInterface': '{name}'.")
        return nic

    def _instances_delete_access_config(self, request=None, **kw):
        req = _request(c.DeleteAccessConfigInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        nic = self._nic(inst, req.network_interface)
        kept = [a for a in nic.access_configs if a.name != req.access_config]
        if len(kept) == len(nic.access_configs):
            raise exceptions.BadRequest(f"Invalid value for field 'accessConfig': '{req.access_config}'.")
        nic.access_configs = kept
        return self._operation(inst.self_link, "deleteAccessConfig", req.request_id)

    def _instances_add_access_config(self, request=None, **kw):
        req = _request(c.AddAccessConfigInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        nic = self._nic(inst, req.network_interface)
        if nic.access_configs:  # GCE: one access config per interface
            raise exceptions.BadRequest("At most one access config currently supported.")
        self._check_nat(req.access_config_resource)
        access = _copy(req.access_config_resource)
        if inst.status != "TERMINATED" or access.nat_i_p:
            self._take_nat(inst, access)
        nic.access_configs = [access]
        return self._operation(inst.self_link, "addAccessConfig", req.request_id)

    def _instances_aggregated_list(self, request=None, **kw):
        req = _request(c.AggregatedListInstancesRequest, request, kw)
        want = _label_filter(req.filter)

        def scopes(_req):
            return [(f"zones/{z}", c.InstancesScopedList(instances=[
                _copy(i) for (iz, _n), i in sorted(self.instances.items())
                if iz == z and all(i.labels.get(k) == v for k, v in want.items())])) for z in ZONES]

        return self._pager("instances", "AggregatedListPager", c.InstanceAggregatedList, scopes, req)

    def _instances_get_serial_port_output(self, request=None, **kw):
        req = _request(c.GetSerialPortOutputInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        return c.SerialPortOutput(contents=self.serial.get(inst.name, ""), next_=len(self.serial.get(inst.name, "")))

    # -- global / regional resources ----------------------------------------------------------
    def _insert(self, store: dict, resource, path: str, request_id: str, prepare=None):
        if replay := self._replay(request_id):
            return replay
        link = self._link(f"{path}/{resource.name}")
        if not NAME.match(resource.name):
            raise exceptions.BadRequest(f"Invalid value for field 'resource.name': '{resource.name}'.")
        if resource.name in store:
            raise exceptions.Conflict(f"The resource '{link}' already exists", errors=[{"reason": "alreadyExists"}])
        resource = _copy(resource)
        if prepare:
            prepare(resource)
        resource.id, resource.self_link = self._new_id(), link
        resource.creation_timestamp = dt.datetime.now(dt.timezone.utc).isoformat()
        store[resource.name] = resource
        return self._operation(link, "insert", request_id)

    def _get(self, store: dict, name: str, path: str):
        if name not in store:
            raise _not_found(self._link(f"{path}/{name}"))
        return _copy(store[name])

    def _delete(self, store: dict, name: str, path: str, request_id: str, users=()):
        self._get(store, name, path)
        link = self._link(f"{path}/{name}")
        if users:
            raise exceptions.BadRequest(
                f"The resource '{link}' is already being used by '{users[0]}'",
                errors=[{"reason": "resourceInUseByAnotherResource"}])
        del store[name]
        return self._operation(link, "delete", request_id)

    def _list(self, service: str, response_cls, store: dict, request):
        return self._pager(service, "ListPager", response_cls,
                           lambda _req: [_copy(v) for _k, v in sorted(store.items())], request)

    def _require_network(self, link: str) -> None:
        if tail(link) not in self.networks:
            raise _not_found(link)

    # networks
    def _networks_insert(self, request=None, **kw):
        req = _request(c.InsertNetworkRequest, request, kw)
        return self._insert(self.networks, req.network_resource, "global/networks", req.request_id)

    def _networks_get(self, request=None, **kw):
        return self._get(self.networks, _request(c.GetNetworkRequest, request, kw).network, "global/networks")

    def _networks_delete(self, request=None, **kw):
        req = _request(c.DeleteNetworkRequest, request, kw)
        users = [r.self_link for store in (self.subnetworks, self.firewalls, self.routes)
                 for r in store.values() if tail(r.network) == req.network]
        return self._delete(self.networks, req.network, "global/networks", req.request_id, users)

    def _networks_list(self, request=None, **kw):
        return self._list("networks", c.NetworkList, self.networks, _request(c.ListNetworksRequest, request, kw))

    # subnetworks (one region)
    def _subnetworks_insert(self, request=None, **kw):
        req = _request(c.InsertSubnetworkRequest, request, kw)
        self._require_network(req.subnetwork_resource.network)

        def prepare(subnet):
            subnet.region = self._link(f"regions/{req.region}")
            subnet.network = self._link(f"global/networks/{tail(subnet.network)}")
            subnet.gateway_address = str(next(ipaddress.ip_network(subnet.ip_cidr_range).hosts()))

        return self._insert(self.subnetworks, req.subnetwork_resource, f"regions/{req.region}/subnetworks",
                            req.request_id, prepare)

    def _subnetworks_get(self, request=None, **kw):
        req = _request(c.GetSubnetworkRequest, request, kw)
        return self._get(self.subnetworks, req.subnetwork, f"regions/{req.region}/subnetworks")

    def _subnetworks_delete(self, request=None, **kw):
        req = _request(c.DeleteSubnetworkRequest, request, kw)
        users = [i.self_link for i in self.instances.values()
                 if i.network_interfaces and tail(i.network_interfaces[0].subnetwork) == req.subnetwork]
        return self._delete(self.subnetworks, req.subnetwork, f"regions/{req.region}/subnetworks", req.request_id, users)

    def _subnetworks_list(self, request=None, **kw):
        return self._list("subnetworks", c.SubnetworkList, self.subnetworks,
                          _request(c.ListSubnetworksRequest, request, kw))

    # firewalls
    def _firewalls_insert(self, request=None, **kw):
        req = _request(c.InsertFirewallRequest, request, kw)
        self._require_network(req.firewall_resource.network)
        return self._insert(self.firewalls, req.firewall_resource, "global/firewalls", req.request_id)

    def _firewalls_get(self, request=None, **kw):
        return self._get(self.firewalls, _request(c.GetFirewallRequest, request, kw).firewall, "global/firewalls")

    def _firewalls_update(self, request=None, **kw):
        req = _request(c.UpdateFirewallRequest, request, kw)
        old = self._get(self.firewalls, req.firewall, "global/firewalls")
        new = _copy(req.firewall_resource)
        new.id, new.self_link, new.creation_timestamp = old.id, old.self_link, old.creation_timestamp
        self.firewalls[req.firewall] = new
        return self._operation(old.self_link, "update", req.request_id)

    def _firewalls_delete(self, request=None, **kw):
        req = _request(c.DeleteFirewallRequest, request, kw)
        return self._delete(self.firewalls, req.firewall, "global/firewalls", req.request_id)

    def _firewalls_list(self, request=None, **kw):
        return self._list("firewalls", c.FirewallList, self.firewalls, _request(c.ListFirewallsRequest, request, kw))

    # addresses (one region; external)
    def _check_region(self, region: str) -> None:
        if region != REGION:
            raise _not_found(self._link(f"regions/{region}"))

    def _addresses_insert(self, request=None, **kw):
        req = _request(c.InsertAddressRequest, request, kw)
        self._check_region(req.region)
        if replay := self._replay(req.request_id):
            return replay
        self._sync_addresses()
        want = req.address_resource
        if want.address_type not in ("", "EXTERNAL"):
            raise exceptions.BadRequest("Invalid value for field 'resource.addressType': the fake has no internal "
                                        "addresses.")
        user = None
        if want.address:  # promotion: only an ephemeral IP an instance holds in the region
            user = next((i for i in self.instances.values() for nic in i.network_interfaces
                         for a in nic.access_configs if a.nat_i_p == want.address), None)
            if user is None or self._reserved(want.address) is not None:
                raise exceptions.BadRequest(f"Requested specific address '{want.address}' is not available.",
                                            errors=[{"reason": "invalid"}])
        if want.name not in self.addresses and len(self.addresses) >= self.address_quota:
            return self._operation(self._link(f"regions/{req.region}/addresses/{want.name}"), "insert",
                                   req.request_id, 403, "QUOTA_EXCEEDED",
                                   quota_exceeded("STATIC_ADDRESSES", self.address_quota))

        def prepare(address):
            address.region = self._link(f"regions/{req.region}")
            address.address_type, address.network_tier = "EXTERNAL", "PREMIUM"
            address.address = want.address or self._free_external_ip()
            address.status = "IN_USE" if user else "RESERVED"
            address.users = [user.self_link] if user else []

        return self._insert(self.addresses, want, f"regions/{req.region}/addresses", req.request_id, prepare)

    def _addresses_get(self, request=None, **kw):
        req = _request(c.GetAddressRequest, request, kw)
        self._check_region(req.region)
        self._sync_addresses()
        return self._get(self.addresses, req.address, f"regions/{req.region}/addresses")

    def _addresses_delete(self, request=None, **kw):
        req = _request(c.DeleteAddressRequest, request, kw)
        self._check_region(req.region)
        self._sync_addresses()
        users = list(self.addresses[req.address].users) if req.address in self.addresses else []
        return self._delete(self.addresses, req.address, f"regions/{req.region}/addresses", req.request_id, users)

    def _addresses_list(self, request=None, **kw):
        req = _request(c.ListAddressesRequest, request, kw)
        self._check_region(req.region)
        self._sync_addresses()
        return self._list("addresses", c.AddressList, self.addresses, req)

    # routes
    def _routes_insert(self, request=None, **kw):
        req = _request(c.InsertRouteRequest, request, kw)
        route = req.route_resource
        self._require_network(route.network)
        robot = description_marks(route.description).get(LABEL_ROBOT)
        if robot in self.fail_route_for:
            self.fail_route_for.discard(robot)
            raise exceptions.BadRequest(f"Invalid value for field 'resource.destRange': '{route.dest_range}'.",
                                        errors=[{"reason": "invalid"}])
        try:
            ipaddress.IPv4Network(route.dest_range)
        except ValueError:
            raise exceptions.BadRequest(f"Invalid value for field 'resource.destRange': '{route.dest_range}'.",
                                        errors=[{"reason": "invalid"}]) from None
        if not 0 <= route.priority <= 65535:
            raise exceptions.BadRequest(f"Invalid value for field 'resource.priority': '{route.priority}'.",
                                        errors=[{"reason": "invalid"}])
        if any(not NAME.match(tag) for tag in route.tags):
            raise exceptions.BadRequest(f"Invalid value for field 'resource.tags': {list(route.tags)}.",
                                        errors=[{"reason": "invalid"}])
        zone, name = route.next_hop_instance.split("/zones/")[-1].split("/instances/")
        hop = self._instance(zone, name)
        if not hop.can_ip_forward:
            raise exceptions.BadRequest(f"Instance '{name}' does not allow IP forwarding.")
        return self._insert(self.routes, route, "global/routes", req.request_id)

    def _routes_get(self, request=None, **kw):
        return self._get(self.routes, _request(c.GetRouteRequest, request, kw).route, "global/routes")

    def _routes_delete(self, request=None, **kw):
        req = _request(c.DeleteRouteRequest, request, kw)
        return self._delete(self.routes, req.route, "global/routes", req.request_id)

    def _routes_list(self, request=None, **kw):
        return self._list("routes", c.RouteList, self.routes, _request(c.ListRoutesRequest, request, kw))

    # images
    def _images_insert(self, request=None, **kw):
        req = _request(c.InsertImageRequest, request, kw)
        zone, disk = req.image_resource.source_disk.split("/zones/")[-1].split("/disks/")
        owner = self.instances.get((zone, disk))
        if owner is None:
            raise _not_found(req.image_resource.source_disk)
        if owner.status == "RUNNING" and not req.force_create:
            raise exceptions.BadRequest(f"The disk resource '{disk}' is already being used by '{owner.self_link}'",
                                        errors=[{"reason": "resourceInUseByAnotherResource"}])

        def prepare(image):
            image.status, image.disk_size_gb, image.archive_size_bytes = "READY", 10, 2_147_483_648

        return self._insert(self.images, req.image_resource, "global/images", req.request_id, prepare)

    def _images_get(self, request=None, **kw):
        return self._get(self.images, _request(c.GetImageRequest, request, kw).image, "global/images")

    def _images_delete(self, request=None, **kw):
        req = _request(c.DeleteImageRequest, request, kw)
        return self._delete(self.images, req.image, "global/images", req.request_id)

    def _images_list(self, request=None, **kw):
        req = _request(c.ListImagesRequest, request, kw)
        want = _label_filter(req.filter)
        return self._pager("images", "ListPager", c.ImageList, lambda _req: [
            _copy(i) for _n, i in sorted(self.images.items()) if all(i.labels.get(k) == v for k, v in want.items())
        ], req)

    # regions
    def _regions_get(self, request=None, **kw):
        req = _request(c.GetRegionRequest, request, kw)
        if req.region != REGION:
            raise _not_found(self._link(f"regions/{req.region}"))
        return c.Region(name=REGION, status="UP", self_link=self._link(f"regions/{REGION}"),
                        zones=[self._link(f"zones/{z}") for z in ZONES],
                        quotas=[c.Quota(metric="CPUS", limit=self.cpu_quota, usage=self._vcpus()),
                                c.Quota(metric="IN_USE_ADDRESSES", limit=self.in_use_address_quota,
                                        usage=self._in_use_addresses()),
                                c.Quota(metric="STATIC_ADDRESSES", limit=self.address_quota, usage=len(self.addresses))])

    def _machine_types_get(self, request=None, **kw):
        req = _request(c.GetMachineTypeRequest, request, kw)
        self._check_zone(req.zone)
        if req.machine_type not in VCPUS:
            raise _not_found(self._link(f"zones/{req.zone}/machineTypes/{req.machine_type}"))
        return c.MachineType(name=req.machine_type, guest_cpus=VCPUS[req.machine_type],
                             self_link=self._link(f"zones/{req.zone}/machineTypes/{req.machine_type}"))

    # -- inspection (not through the API) -------------------------------------------------------
    def marks(self):
        """(kind, id, marks) of every resource: labels, or the ownership line of a description."""
        for inst in self.instances.values():
            yield "instance", str(inst.id), dict(inst.labels)
        for image in self.images.values():
            yield "image", str(image.id), dict(image.labels)
        for kind, store in (("network", self.networks), ("subnet", self.subnetworks),
                            ("firewall", self.firewalls), ("route", self.routes), ("address", self.addresses)):
            for item in store.values():
                yield kind, str(item.id), description_marks(item.description)


class GcpHarness:
    kind = "gcp"

    def __init__(self, tmp_path: Path, fake: FakeProject | None = None, inv: Inventory | None = None) -> None:
        self.fake = fake or FakeProject()
        self.inv = inv or inventory()
        self.provider = self.new_provider(self.inv, tmp_path / "store")

    def new_provider(self, inv: Inventory, workdir: Path) -> GcpProvider:
        """A GcpProvider (a fresh process, as far as ccrp knows) on this fake project."""
        provider = GcpProvider(inv, workdir, clients=self.fake.clients)
        provider.client.backoff = specs.FAST
        return provider

    def spec(self, robot: str, index: int) -> CloneSpec:
        return specs.clone_spec(self.inv, robot, index, PUBLIC_IMAGE)

    def kill(self, provider_id: str) -> None:
        with self.fake.lock:  # as instances.delete does: the routes and reserved addresses stay
            [key] = [k for k, i in self.fake.instances.items() if str(i.id) == provider_id]
            del self.fake.instances[key]

    def fail_create_after_instance(self, robot: str) -> None:
        self.fake.fail_route_for.add(robot)  # the instance is up, its VPN route is refused

    def owned_ids(self, robot: str | None = None) -> set[str]:
        with self.fake.lock:
            return {rid for _kind, rid, marks in self.fake.marks()
                    if marks.get(LABEL_MANAGED) == "true" and marks.get(LABEL_FLEET) == FLEET
                    and (robot is None or marks.get(LABEL_ROBOT) == robot)}

    def _raw_instance(self, name: str, labels: dict[str, str]) -> str:
        with self.fake.lock:
            inst = c.Instance(name=name, labels=labels, machine_type=f"zones/{ZONES[0]}/machineTypes/e2-medium")
            return str(self.fake.store_instance(ZONES[0], inst).id)

    def add_foreign(self) -> str:
        return self._raw_instance(f"ccrp-{FLEET}-cri-foreign", {})

    def add_leak(self) -> str:
        return self._raw_instance(f"ccrp-{FLEET}-cri-leak", owner_labels(FLEET, "clone", "leak"))

    def exists(self, resource_id: str) -> bool:
        with self.fake.lock:
            return any(rid == resource_id for _kind, rid, _marks in self.fake.marks())

    def public_ingress(self) -> set[tuple[str, int, str]]:
        common = self.inv.common.cidr
        found = set()
        with self.fake.lock:
            for rule in self.fake.firewalls.values():
                if description_marks(rule.description).get(LABEL_FLEET) != FLEET or rule.direction != "INGRESS":
                    continue
                for source in rule.source_ranges:
                    if ipaddress.ip_network(source).subnet_of(common):
                        continue
                    for allowed in rule.allowed:
                        for port in allowed.ports or ["0"]:
                            low, _, high = port.partition("-")
                            for p in range(int(low), int(high or low) + 1):
                                found.add((allowed.I_p_protocol, p, source))
        return found

    def _clone(self, robot: str) -> c.Instance | None:
        with self.fake.lock:
            return next((i for i in self.fake.instances.values()
                         if i.labels.get(LABEL_FLEET) == FLEET and i.labels.get(LABEL_ROBOT) == robot), None)

    def user_data_sent(self, robot: str) -> bytes:
        inst = self._clone(robot)
        assert inst is not None, f"no instance for {robot}"
        return next(item.value for item in inst.metadata.items if item.key == "user-data").encode()

    def throttle(self, fraction: float) -> None:
        self.fake.throttled = fraction

    def delay(self, seconds: float) -> None:
        self.fake.latency = seconds

    def instance_roles(self, robot: str) -> list[str]:
        with self.fake.lock:
            return [i.labels.get(LABEL_ROLE, "") for i in self.fake.instances.values()
                    if i.labels.get(LABEL_FLEET) == FLEET and i.labels.get(LABEL_ROBOT) == robot]

    def instances_for(self, robot: str) -> int:
        with self.fake.lock:
            return sum(1 for i in self.fake.instances.values()
                       if i.labels.get(LABEL_FLEET) == FLEET and i.labels.get(LABEL_ROBOT) == robot)

    def api_calls(self) -> Counter:
        return Counter(self.fake.calls)


@contextlib.contextmanager
def make_harness(tmp_path: Path):
    # Everything lives in memory: nothing to stop on exit.
    yield GcpHarness(tmp_path)
