"""The in-memory GCE of the contract suite (tests/contract/harness_gcp.FakeProject) with instances
that really boot: opt-in, `BootingProject(boot=CloudBoot())`; FakeProject itself stays in memory.

Each instance is a systemd container (cloudboot.py) booted from its boot disk's image with the
`user-data` value of its metadata (`user-data-encoding: base64` honoured). On GCE, cloud-init's GCE
datasource reads that key from the metadata server; here the NoCloud seed carries it, the stand-in
for that datasource. The stock `projects/debian-cloud/global/images/family/debian-12` (and any
debian-12 image of debian-cloud) is cloudboot.DEBIAN_12.

What differs from Debian's real GCE image: DEBIAN_12 has cloud-init (with NoCloud) and no Google
guest agent. The guest agent's jobs are not played: the `ssh-keys` metadata installs no keys (the
user-data's login user carries the operator key) and a `startup-script` is kept in the metadata
but not run. ccrp's startup-script for debian-cloud images installs cloud-init and steps aside when
cloud-init is enabled already (/run/cloud-init/enabled), which on this image it always is, so
running it would change nothing; the user-data it would hand to cloud-init is seeded instead.

Networks: a subnetwork is a Docker network with the subnetwork's range (its gateway, the first
host, is this host), made when the first instance boots on it (or beforehand, `reserve_subnet`);
the container's interface has the instance's networkIP. The internet is a Docker network of the
fake's own (a free /24 of 172.27.0.0/16 unless `internet_cidr` is given; its .1 is this host): an
access config's external NAT IP is an address there, on a second interface of the container, so
ccrp (and a simulated robot on that network) reach the instance's public IP. As on GCE, an
ephemeral IP is released when the instance stops and a new one comes with the next start, while a
reserved address (addresses.insert: a free IP of the internet network, or an instance's ephemeral
IP promoted) stays the instance's: its interface comes back with the same IP at every start.

Operations are honest about time: instances.insert, start, stop, delete and images.insert answer
a RUNNING operation that is DONE once the container runs / stopped / is gone / is committed, and
polling it is an API call (zoneOperations.get, subject to `throttled` like any other). A boot or a
capture that fails ends its operation with an error (a failed insert leaves no instance).
instances.get / aggregatedList show TERMINATED for a container that stopped from inside.
get_serial_port_output is the container's console (serial port 1: cloud-init's output, the SSH
host keys' fingerprints included). images.insert from an instance's boot disk is `docker commit`
(a tmpfs inside is not captured), and instances boot from that image; deleting the image removes it.

Not enforced when booting: firewall rules (every port of a container is open to this host and to
its networks' peers), routes (the robots' VPN subnets are not routed to the next-hop instance by
Docker, nor is an entry gateway's route 0.0.0.0/0 the clones' way out: a clone without an access
config reaches out through its subnetwork's Docker network, as this host routes it), network tags,
service accounts, machine types beyond the CPU quota. An entry gateway (provider.entry: gateway)
is an instance like any other: its access config's address is on its internet interface, where
the robots dial it, and its own rules forward their ports to the clones on the subnetwork.

Faults for scenarios: `quota_once(n)` refuses the next n instance inserts with HTTP 403 quotaExceeded
(Quota 'CPUS' exceeded: GCE's usual answer, no operation), and the harness's `exhausted` zones
(ZONE_RESOURCE_POOL_EXHAUSTED operation errors) and `throttled` fraction work as in the contract
suite. As there, a repeated requestId gets its first operation back, a failed one included.
"""

from __future__ import annotations

import base64
import ipaddress
import threading
from typing import TYPE_CHECKING

from google.api_core import exceptions
from google.cloud import compute_v1 as c

from ccrp_cli.providers.gcp.ownership import tail
from tests.contract.harness_gcp import (
    PROJECT,
    FakeOperation,
    FakeProject,
    _copy,
    _not_found,
    _request,
    quota_exceeded,
)

from .cloudboot import DEBIAN_12

if TYPE_CHECKING:
    from .cloudboot import CloudBoot

INTERNET_RANGE = "172.27.0.0/16"  # the fake's internet: a free /24 of it, a Docker network
DEBIAN_PROJECT = "debian-cloud"
DEBIAN_FAMILY = "debian-12"
DEBIAN_IMAGE = "debian-12-bookworm-v20240709"  # the name the family resolves to (a GCE-style version)
SERIAL_MAX = 1024 * 1024  # GCE keeps the last 1 MiB of serial port output


class BootingProject(FakeProject):
    """FakeProject whose instances are containers, images Docker images, subnetworks and the
    internet Docker networks (see the module's docstring)."""

    def __init__(self, boot: CloudBoot, internet_cidr: str | None = None, cpu_quota: float = 24) -> None:
        self.boot = boot
        self.docker_images: dict[str, str] = {}      # image name -> Docker image it boots
        self.subnet_nets: dict[str, str] = {}        # subnetwork range -> Docker network
        self.threads: set[threading.Thread] = set()  # boots, stops, deletes, captures in flight
        self.quota_refusals = 0
        self.last_console: dict[str, str] = {}       # instance name -> its console when it was deleted
        super().__init__(cpu_quota=cpu_quota)
        if internet_cidr:
            self.internet_net, self.internet_cidr = boot.ensure_network("internet", internet_cidr), internet_cidr
        else:
            self.internet_net, self.internet_cidr = boot.claim_network("internet", INTERNET_RANGE)
        pool = ipaddress.IPv4Network(self.internet_cidr)
        self.internet_gateway = str(next(pool.hosts()))  # this host's address on the internet
        self._nat_pool = [str(h) for h in pool.hosts() if str(h) != self.internet_gateway]

    # -- plumbing -------------------------------------------------------------------------------
    def _clients(self):
        clients = super()._clients()
        # What the contract suite does not call but a booting GCE needs.
        clients.instances.stop.side_effect = self._endpoint("instances.stop", self._instances_stop)
        clients.images.get_from_family.side_effect = self._endpoint("images.get_from_family",
                                                                    self._images_get_from_family)
        return clients

    def _future(self, op: c.Operation) -> FakeOperation:
        """The operation as the SDK's future: each poll is a zoneOperations.get call (throttled
        like any call) answering a copy of `op`, which the work's thread marks DONE."""
        def refresh(*_args, **_kw):
            return _copy(op)

        return FakeOperation.make(self._endpoint("operations.get", refresh), lambda: None, _copy(op))

    def _operation(self, target: str, kind: str, request_id: str = "", code: int = 0, error: str = "",
                   message: str = "") -> FakeOperation:
        done = super()._operation(target, kind, request_id, code, error, message)._extended_operation
        return self._future(done)

    def _pending(self, target: str, kind: str, request_id: str, work, finished=None) -> FakeOperation:
        """A RUNNING operation; `work()` runs in a thread of its own and the operation is DONE when
        it returns (with its exception as the operation's error, after `finished(exc)`)."""
        self._ops += 1
        op = c.Operation(name=f"operation-{self._ops}", operation_type=kind, target_link=target,
                         status=c.Operation.Status.RUNNING)
        if request_id:
            self.replies[request_id] = op

        def run() -> None:
            failure = None
            try:
                work()
            except Exception as exc:  # noqa: BLE001 - the operation reports it
                failure = exc
            with self.lock:
                if finished is not None:
                    finished(failure)
                if failure is not None:
                    op.http_error_status_code = getattr(failure, "code", None) or 500
                    op.http_error_message = f"{kind}: {failure}"
                    op.error = c.Error(errors=[c.Errors(code=getattr(failure, "gce_code", "INTERNAL_ERROR"),
                                                        message=str(failure))])
                op.status = c.Operation.Status.DONE
                self.threads.discard(threading.current_thread())

        thread = threading.Thread(target=run, name=f"fake-gce-{kind}-{tail(target)}", daemon=True)
        self.threads.add(thread)
        thread.start()
        return self._future(op)

    def wait_idle(self, timeout: float = 120) -> None:
        """Until no boot, stop, delete or capture is in flight (before cleaning up)."""
        with self.lock:
            threads = list(self.threads)
        for thread in threads:
            thread.join(timeout)

    # -- networks -------------------------------------------------------------------------------
    def reserve_subnet(self, within: str, prefix: int = 24) -> str:
        """A free range for a subnetwork to come (its Docker network made now, so that no other
        Docker network takes the range meanwhile): returns the range."""
        net, cidr = self.boot.claim_network(f"subnet-{len(self.subnet_nets)}", within, prefix)
        with self.lock:
            self.subnet_nets[cidr] = net
        return cidr

    def _subnet_net(self, subnet: c.Subnetwork) -> str:
        with self.lock:
            net = self.subnet_nets.get(subnet.ip_cidr_range)
        if net is None:
            net = self.boot.ensure_network(f"subnet-{subnet.ip_cidr_range.replace('/', '_')}", subnet.ip_cidr_range,
                                           subnet.gateway_address or None)
            with self.lock:
                self.subnet_nets[subnet.ip_cidr_range] = net
        return net

    def _external_pool(self) -> list[str]:
        return self._nat_pool  # FakeProject._free_external_ip hands out addresses of the internet network

    # -- images ---------------------------------------------------------------------------------
    def _debian(self) -> c.Image:
        link = f"https://www.googleapis.com/compute/v1/projects/{DEBIAN_PROJECT}/global/images/{DEBIAN_IMAGE}"
        return c.Image(name=DEBIAN_IMAGE, family=DEBIAN_FAMILY, status="READY", self_link=link, id=1_200_000_001,
                       disk_size_gb=10, creation_timestamp="2024-07-09T00:00:00.000-07:00",
                       description="Debian, Debian GNU/Linux, 12 (bookworm), amd64 built on 20240709")

    @staticmethod
    def _is_debian(source: str) -> bool:
        path = source.split("/projects/", 1)[-1].removeprefix("projects/")
        return path in (f"{DEBIAN_PROJECT}/global/images/family/{DEBIAN_FAMILY}",
                        f"{DEBIAN_PROJECT}/global/images/{DEBIAN_IMAGE}")

    def _image_for(self, source: str):
        return self._debian() if self._is_debian(source) else super()._image_for(source)

    def _disk_of(self, source: str) -> str | None:
        """The Docker image an instance booted from `source` starts from (None: no disk here)."""
        if self._is_debian(source):
            return DEBIAN_12
        return self.docker_images.get(tail(source)) if f"projects/{PROJECT}/global/images/" in source else None

    def _images_get(self, request=None, **kw):
        req = _request(c.GetImageRequest, request, kw)
        if req.project == DEBIAN_PROJECT:
            if req.image != DEBIAN_IMAGE:
                raise _not_found(f"projects/{DEBIAN_PROJECT}/global/images/{req.image}")
            return self._debian()
        if req.project != PROJECT:
            raise _not_found(f"projects/{req.project}/global/images/{req.image}")
        return super()._images_get(req)

    def _images_get_from_family(self, request=None, **kw):
        req = _request(c.GetFromFamilyImageRequest, request, kw)
        if (req.project, req.family) == (DEBIAN_PROJECT, DEBIAN_FAMILY):
            return self._debian()
        found = [i for i in self.images.values() if req.project == PROJECT and i.family == req.family]
        if not found:
            raise _not_found(f"projects/{req.project}/global/images/family/{req.family}")
        return _copy(max(found, key=lambda i: i.creation_timestamp))

    def _images_insert(self, request=None, **kw):
        req = _request(c.InsertImageRequest, request, kw)
        if req.request_id and req.request_id in self.replies:
            return self._future(self.replies[req.request_id])
        op = super()._images_insert(req)
        if op.error_code:
            return op
        image = self.images[req.image_resource.name]
        zone, disk = req.image_resource.source_disk.split("/zones/")[-1].split("/disks/")
        owner = self.instances[(zone, disk)]
        server = str(owner.id)
        image.status, image.archive_size_bytes = "PENDING", 0

        def capture() -> None:
            if not self.boot.has(server):
                raise RuntimeError(f"disk {disk} is not attached to a running instance")
            ref = self.boot.capture(server, image.name)
            size = self.boot.client.images.get(ref).attrs.get("Size") or 0
            with self.lock:
                self.docker_images[image.name] = ref
                image.archive_size_bytes = size

        def finished(exc) -> None:
            image.status = "FAILED" if exc else "READY"

        return self._pending(image.self_link, "insert", req.request_id, capture, finished)

    def _images_delete(self, request=None, **kw):
        req = _request(c.DeleteImageRequest, request, kw)
        op = super()._images_delete(req)
        ref = self.docker_images.pop(req.image, None)
        if ref is not None and ref in self.boot.images:  # captured by this run: the disk goes with the image
            self.boot.remove_image(ref)
        return op

    # -- instances ------------------------------------------------------------------------------
    def quota_once(self, n: int = 1) -> None:
        """The next n instance inserts are refused over the regional CPUS quota (HTTP 403 quotaExceeded)."""
        with self.lock:
            self.quota_refusals += n

    def _instances_insert(self, request=None, **kw):
        req = _request(c.InsertInstanceRequest, request, kw)
        if req.request_id and req.request_id in self.replies:
            return self._future(self.replies[req.request_id])
        boot_disks = [d for d in req.instance_resource.disks if d.boot]
        source = boot_disks[0].initialize_params.source_image if boot_disks else ""
        if self.quota_refusals and (req.zone, req.instance_resource.name) not in self.instances:
            # GCE's usual answer to an insert over a regional quota: the request itself is refused
            # (no operation, so its requestId is not spent).
            self.quota_refusals -= 1
            raise exceptions.Forbidden(quota_exceeded("CPUS", self.cpu_quota),
                                       errors=[{"reason": "quotaExceeded", "domain": "usageLimits"}])
        op = super()._instances_insert(req)
        if op.error_code:
            return op
        inst = self.instances[(req.zone, req.instance_resource.name)]
        inst.status = "STAGING"
        nic = inst.network_interfaces[0]
        subnet = self.subnetworks[tail(nic.subnetwork)]
        disk = self._disk_of(source)
        metadata = {item.key: item.value for item in inst.metadata.items}
        user_data = metadata.get("user-data", "").encode()
        if metadata.get("user-data-encoding") == "base64":
            user_data = base64.b64decode(user_data)
        server, name, key = str(inst.id), inst.name, (req.zone, inst.name)
        public = nic.access_configs[0].nat_i_p if nic.access_configs else None

        def spawn() -> None:
            if disk is None:
                raise _Refused(400, "INVALID_IMAGE", f"image {source} has no disk in this fake: boot from "
                                                     f"projects/{DEBIAN_PROJECT}/global/images/family/{DEBIAN_FAMILY} or a "
                                                     "captured image")
            networks = [(self._subnet_net(subnet), nic.network_i_p)]
            if public:
                networks.append((self.internet_net, public))
            self.boot.boot(server, name, disk, user_data, networks)

        def finished(exc) -> None:
            if exc is None:
                inst.status = "RUNNING"
                return
            self.instances.pop(key, None)  # GCE: a failed insert leaves no instance
            self.boot.delete(server)

        return self._pending(inst.self_link, "insert", req.request_id, spawn, finished)

    def _sync(self, inst: c.Instance) -> None:
        """Power state as the hypervisor sees it: a container stopped from inside is TERMINATED."""
        server = str(inst.id)
        if inst.status == "RUNNING" and self.boot.has(server) and self.boot.state(server) != "running":
            inst.status = "TERMINATED"
            self._release_nat(inst)

    def _release_nat(self, inst: c.Instance) -> None:
        """The stopped container leaves the internet; an ephemeral IP goes with it (not a reserved one)."""
        self._stop_nat(inst)
        if self.boot.has(str(inst.id)):
            self.boot.detach(str(inst.id), self.internet_net)

    def _instances_get(self, request=None, **kw):
        req = _request(c.GetInstanceRequest, request, kw)
        self._sync(self._instance(req.zone, req.instance))
        return super()._instances_get(req)

    def _instances_aggregated_list(self, request=None, **kw):
        for inst in self.instances.values():
            self._sync(inst)
        return super()._instances_aggregated_list(request, **kw)

    def _instances_get_serial_port_output(self, request=None, **kw):
        req = _request(c.GetSerialPortOutputInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        server = str(inst.id)
        text = self.boot.console(server).replace("\r\n", "\n") if self.boot.has(server) else ""
        data = text.encode()
        start = max(int(req.start or 0), len(data) - SERIAL_MAX)
        return c.SerialPortOutput(contents=data[start:].decode(errors="replace"), start=start, next_=len(data),
                                  self_link=f"{inst.self_link}/serialPort")

    def _instances_stop(self, request=None, **kw):
        req = _request(c.StopInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        self._sync(inst)
        if inst.status != "RUNNING":
            return self._operation(inst.self_link, "stop", req.request_id)  # GCE: a no-op when not running
        inst.status = "STOPPING"

        def finished(exc) -> None:
            inst.status = "RUNNING" if exc else "TERMINATED"
            if exc is None:
                self._release_nat(inst)

        return self._pending(inst.self_link, "stop", req.request_id, lambda: self.boot.stop(str(inst.id)), finished)

    def _instances_start(self, request=None, **kw):
        req = _request(c.StartInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        self._sync(inst)
        if inst.status != "TERMINATED":
            return self._operation(inst.self_link, "start", req.request_id)
        inst.status = "STAGING"
        server = str(inst.id)
        accesses = [a for nic in inst.network_interfaces for a in nic.access_configs]
        self._start_nat(inst)  # a new ephemeral external IP; a reserved address is kept

        def start() -> None:
            if accesses:
                self.boot.attach(server, self.internet_net, accesses[0].nat_i_p)
            self.boot.start(server)

        def finished(exc) -> None:
            inst.status = "TERMINATED" if exc else "RUNNING"

        return self._pending(inst.self_link, "start", req.request_id, start, finished)

    def _instances_delete(self, request=None, **kw):
        req = _request(c.DeleteInstanceRequest, request, kw)
        inst = self._instance(req.zone, req.instance)
        inst.status = "STOPPING"
        key, server, name = (req.zone, req.instance), str(inst.id), inst.name

        def delete() -> None:
            if self.boot.has(server):
                console = self.boot.console(server).replace("\r\n", "\n")
                with self.lock:
                    self.last_console[name] = console
            self.boot.delete(server)

        def finished(exc) -> None:
            if exc is None and self.instances.get(key) is inst:  # routes through it stay, as on GCE
                del self.instances[key]

        return self._pending(inst.self_link, "delete", req.request_id, delete, finished)

    def _wire_nat(self, inst: c.Instance) -> None:
        """A running container's internet interface follows its access config."""
        server = str(inst.id)
        if not self.boot.has(server) or self.boot.state(server) != "running":
            return
        ips = [a.nat_i_p for nic in inst.network_interfaces for a in nic.access_configs if a.nat_i_p]
        if ips:
            self.boot.attach(server, self.internet_net, ips[0])
        else:
            self.boot.detach(server, self.internet_net)

    def _instances_delete_access_config(self, request=None, **kw):
        req = _request(c.DeleteAccessConfigInstanceRequest, request, kw)
        op = super()._instances_delete_access_config(req)
        self._wire_nat(self._instance(req.zone, req.instance))
        return op

    def _instances_add_access_config(self, request=None, **kw):
        req = _request(c.AddAccessConfigInstanceRequest, request, kw)
        op = super()._instances_add_access_config(req)
        self._wire_nat(self._instance(req.zone, req.instance))
        return op

    # -- inspection -----------------------------------------------------------------------------
    def container_of(self, name: str):
        """The Docker container of instance `name` (tests look inside), or None."""
        with self.lock:
            inst = next((i for (_z, n), i in self.instances.items() if n == name), None)
        if inst is None or not self.boot.has(str(inst.id)):
            return None
        return self.boot.containers[str(inst.id)]


class _Refused(Exception):
    """A failure GCE reports as an operation error with this HTTP status and error code."""

    def __init__(self, code: int, gce_code: str, message: str) -> None:
        super().__init__(message)
        self.code, self.gce_code = code, gce_code
