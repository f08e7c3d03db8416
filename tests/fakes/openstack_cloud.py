"""A small in-memory OpenStack (Keystone, Nova, Neutron, Glance) behind requests-mock.

openstacksdk runs unmodified against it: it authenticates against the Keystone catalog that
openstacksdk's own `openstack.fixture.connection.ConnectionFixture` builds (compute at
https://compute.example.com/v2.1/, network at https://network.example.com, image at
https://image.example.com), discovers versions, negotiates microversions and builds and parses
every request itself. The fake keeps just enough of each API to be honest about what a real cloud
refuses: a fixed IP used twice, a router with interfaces, a subnet or network still in use, quota,
user-data over Nova's limit, and servers the scheduler cannot place ("No valid host was found").

Knobs for tests: `throttle(fraction)` (429/503 before the fake), `delay(seconds)`, `no_capacity`
zones, the project's quotas (`max_instances`, `max_cores`, `max_ram`, `max_fips`), `fail_fip_for`
robots, `fail_next` operations; `calls` counts (METHOD, path template).

Two transports share one request handler (`handle`): requests-mock mounted on a Connection's
session in this process (`attach`), or a real HTTP server on 127.0.0.1 for other processes
(openstack_http.py), whose Keystone catalog and version documents carry the served URLs.

Servers that really boot (opt-in: `FakeOpenStack(boot=CloudBoot())`, see cloudboot.py): each
server is a systemd container booted from its Glance image's Docker image with the user-data Nova
received (NoCloud seed; the key pair's public key in the meta-data), BUILD until the container
runs, then ACTIVE. Each Neutron subnet a server's port is on is a Docker network with the
subnet's CIDR and gateway (the host holds the gateway address, as the router would), and the
container's interface has the port's fixed IP. The external network's floating-IP pool is a
Docker network the fake claims (a free /24 of 172.29.0.0/16 unless `fip_cidr` is given; its .1 is
the host): associating a floating IP connects the container to it with that address, so the host
(ccrp) and simulated robots on that network reach the server's public IP. The console is the
container's console; os-stop/os-start stop and start it; delete removes it; createImage commits
it into a Docker image recorded in Glance, which servers boot from. Glance has a public
`debian-12-genericcloud-amd64` image (cloudboot.DEBIAN_12); images without a Docker image of their
own (ubuntu-20.04) cannot boot: such a server goes to ERROR. The image's default user is `debian`;
`vendor_data=cloudboot.vendor_data_default_user("ubuntu")` renames it as an operator's vendor-data
could (ccrp logs in as `ubuntu`, the Ubuntu images' user).
Not enforced when booting: security groups (every container port is open to the host and to the
other containers on its networks), allowed-address pairs and port security, routers (every network
reaches the outside through Docker's NAT, router or not).
"""

from __future__ import annotations

import base64
import ipaddress
import json
import os
import re
import threading
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import parse_qs, urlparse

import requests_mock
from openstack.fixture.connection import ConnectionFixture

from .openstack_neutron import ApiError, NeutronApi, new_id, now

if TYPE_CHECKING:
    from .cloudboot import CloudBoot

NO_VALID_HOST = "No valid host was found. There are not enough hosts available."
# What Zed's Nova says when hosts were found but the build failed on each (scripts/openstack.sh's
# cloud said it for a config drive nova-compute could not write).
BUILD_FAILED = ("Exceeded maximum number of retries. Exhausted all hosts available for retrying build failures "
                "for instance {id}.")
MAX_USER_DATA_B64 = 65_535  # Nova's limit on the base64 text
FIP_POOL = ipaddress.IPv4Network("203.0.113.0/24")  # TEST-NET-3: never contacted
BOOT_FIP_RANGE = "172.29.0.0/16"  # booting: the floating-IP pool is a free /24 of it, a Docker network
BOOT_IMAGE = "debian-12-genericcloud-amd64"  # booting: the public image of cloudboot.DEBIAN_12
HOSTS = ("identity", "compute", "network", "image")


# Path segments that name one resource: after these collections, or anything that is a UUID.
_NAMED = {"servers", "flavors", "os-keypairs", "images", "tags", "networks", "subnets", "routers", "ports", "quotas",
          "floatingips", "security-groups", "security-group-rules"}


def _template(path: str) -> str:
    """/v2.1/servers/<uuid>/action -> /v2.1/servers/{id}/action (the operation, for counting)."""
    parts = path.split("/")
    out = [p if i == 0 or (parts[i - 1] not in _NAMED and not re.fullmatch(r"[0-9a-f-]{36}", p))
           or p == "detail" else "{id}" for i, p in enumerate(parts)]
    return "/".join(out)


class Context:
    """What a handler sets on its response, as requests-mock's context has it."""

    def __init__(self) -> None:
        self.status_code = 200
        self.headers: dict[str, str] = {}


class FakeOpenStack(NeutronApi):
    def __init__(self, boot: CloudBoot | None = None, fip_cidr: str | None = None,
                 vendor_data: bytes | None = None) -> None:
        self.fixture = ConnectionFixture()  # openstacksdk's own catalog + token
        self.project_id = self.fixture.project_id
        self.lock = threading.RLock()
        self.calls: Counter = Counter()
        self.throttle_fraction = 0.0
        self._n = 0
        self.delay_s = 0.0
        self.no_capacity: set[str] = set()  # zones where the scheduler finds no host
        self.build_fails: set[str] = set()  # zones whose hosts fail every build
        # The project's quotas (Nova: instances, cores, RAM in MB; Neutron: floating IPs), enforced
        # at create and reported with their usage (compute /limits, network /quotas/<id>/details)
        # from what exists. Small, as a new project's are: the benchmark raises them.
        self.max_instances = 100
        self.max_cores = 200
        self.max_ram = 409_600
        self.max_fips = 50  # Neutron's default (quota_floatingip), as in a new project
        self.refuse_auth = False  # Keystone refuses the credentials (401), as for a wrong password
        self.fail_fip_for: set[str] = set()  # robots whose next floating IP request fails
        self.fail_next: dict[tuple[str, str], tuple[int, str]] = {}  # (METHOD, "host:/template") -> one error
        # name -> resource dict, per collection (Neutron/Glance/Nova shapes, as on the wire)
        self.servers: dict[str, dict] = {}
        self.networks: dict[str, dict] = {}
        self.subnets: dict[str, dict] = {}
        self.routers: dict[str, dict] = {}
        self.ports: dict[str, dict] = {}
        self.fips: dict[str, dict] = {}
        self.sgs: dict[str, dict] = {}
        self.images: dict[str, dict] = {}
        self.flavors: dict[str, dict] = {}
        self.keypairs: dict[str, dict] = {}
        self._local = threading.local()  # the served root URL of the request being handled
        self.boot = boot
        self.vendor_data = vendor_data  # booting: given to every server (cloudboot.vendor_data_default_user)
        if boot is None:
            self._fip_hosts = iter(FIP_POOL.hosts())
        else:
            self._init_boot(fip_cidr)
        self.adapter = self._routes()
        ext = self.add("networks", {"name": "public", "router:external": True})
        self.add("subnets", {"network_id": ext["id"], "cidr": str(FIP_POOL) if boot is None else self.fip_cidr,
                             "name": "public-v4", **({} if boot is None else {"gateway_ip": self.fip_gateway})})
        self.add_flavor("m1.small")
        self.add_image("ubuntu-20.04")
        if boot is not None:
            from .cloudboot import DEBIAN_12

            image = self.add_image(BOOT_IMAGE, os_distro="debian", os_version="12", owner="debian-cloud-team")
            self.docker_images[image["id"]] = DEBIAN_12

    def _init_boot(self, fip_cidr: str | None) -> None:
        """Booting: the floating-IP pool as a Docker network of the fake's own; bookkeeping."""
        boot = self.boot
        if fip_cidr:
            self.fip_network, self.fip_cidr = boot.ensure_network("public", fip_cidr), fip_cidr
        else:
            self.fip_network, self.fip_cidr = boot.claim_network("public", BOOT_FIP_RANGE)
        pool = ipaddress.IPv4Network(self.fip_cidr)
        self.fip_gateway = str(next(pool.hosts()))  # the host's address on it
        self._fip_hosts = (h for h in pool.hosts() if str(h) != self.fip_gateway)
        self.docker_images: dict[str, str] = {}  # Glance image id -> Docker image
        self._subnet_nets: dict[str, str] = {}   # Neutron subnet id -> Docker network
        self._threads: dict[str, threading.Thread] = {}  # server id -> its boot

    # -- seeding --------------------------------------------------------------------------------
    def add(self, collection: str, body: dict) -> dict:
        """A Neutron-style resource with the defaults the API fills in."""
        res = {"id": new_id(), "name": "", "tags": [], "project_id": self.project_id,
               "tenant_id": self.project_id, "description": "", "created_at": now(), **body}
        if collection == "networks":
            res.setdefault("router:external", False)
            res.setdefault("subnets", [])
            res.setdefault("status", "ACTIVE")
        if collection == "subnets":
            res.setdefault("ip_version", 4)  # Neutron answers it for every subnet
        getattr(self, collection)[res["id"]] = res
        return res

    def add_flavor(self, name: str, **sizes) -> dict:
        flavor = {"id": new_id(), "name": name, "vcpus": 2, "ram": 4096, "disk": 20,
                  "os-flavor-access:is_public": True, "OS-FLV-EXT-DATA:ephemeral": 0, "swap": 0, **sizes}
        self.flavors[flavor["id"]] = flavor
        return flavor

    def add_image(self, name: str, **props) -> dict:
        image = {"id": new_id(), "name": name, "status": "active", "visibility": "public", "tags": [],
                 "created_at": now(), "updated_at": now(), "size": 2_000_000_000, "owner": self.project_id,
                 "disk_format": "qcow2", "container_format": "bare", **props}
        self.images[image["id"]] = image
        return image

    # -- requests-mock wiring -------------------------------------------------------------------
    def attach(self, conn) -> None:
        """Route an openstack.Connection's HTTP to the fake: requests-mock's transport adapter
        mounted on its keystoneauth session (unmatched URLs raise NoMockAddress). Not
        requests_mock.Mocker: that serialises every request in the process behind one lock (10 s
        timeout), which would hide the concurrency of parallel clones and break slow benchmarks."""
        for prefix in ("https://", "http://"):
            conn.session.session.mount(prefix, self.adapter)

    def _routes(self) -> requests_mock.Adapter:
        adapter = requests_mock.Adapter()
        for host in HOSTS:
            adapter.register_uri(requests_mock.ANY, re.compile(rf"https://{host}\.example\.com(/|$)"), json=self._respond)
        return adapter

    def _respond(self, request, context):
        """requests-mock's callback: https://<service>.example.com/<path>."""
        url = urlparse(request.url)
        return self.handle(request.method, url.hostname.split(".")[0], request.path, url.query, request.body, context)

    def handle(self, method: str, host: str, path: str, query_string: str, body: bytes | str | None, context,
               root: str | None = None):
        """One API request, whatever carried it: `host` is the service (identity, compute, network,
        image), `path` the path under it; sets context.status_code/headers and returns the JSON
        body (None: no body). `root` is the served base URL (http://127.0.0.1:PORT) when the
        request came over HTTP: the catalog and version documents then point there."""
        self._local.root = root
        path = path.rstrip("/") or "/"
        query = {k: v for k, v in parse_qs(query_string, keep_blank_values=True).items()}
        template = _template(path)
        op = (method, f"{host}:{template}")
        if self.delay_s:
            time.sleep(self.delay_s)  # outside the lock: concurrent callers overlap as on a real cloud
        context.headers["Content-Type"] = "application/json"
        with self.lock:
            self.calls[op] += 1
            if host != "identity" and self._throttled():
                context.status_code = 429 if self._n % 2 else 503
                context.headers["Retry-After"] = "0"
                return {"message": "Rate limit exceeded" if context.status_code == 429 else "Service Unavailable"}
            body = json.loads(body) if body else {}
            try:
                if op in self.fail_next:
                    raise ApiError(*self.fail_next.pop(op))
                answer = getattr(self, f"_{host}")(method, path, query, body, context)
                if self.boot is not None and host == "network" and method != "GET":
                    self._rewire()  # a port or floating IP may have moved
                return answer
            except ApiError as err:
                context.status_code = err.status
                if host == "network":
                    return {"NeutronError": {"type": err.kind, "message": err.message, "detail": ""}}
                return {err.kind[0].lower() + err.kind[1:]: {"code": err.status, "message": err.message}}

    def _throttled(self) -> bool:
        """Every (1/fraction)-th service call, deterministically (tests stay reproducible)."""
        self._n += 1
        f = self.throttle_fraction
        return int(self._n * f) > int((self._n - 1) * f)

    # -- Keystone -------------------------------------------------------------------------------
    def _identity(self, method, path, query, body, context):
        if method == "POST" and path == "/v3/auth/tokens" and self.refuse_auth:
            raise ApiError(401, "The request you have made requires authentication.", "Unauthorized")
        if method == "POST" and path == "/v3/auth/tokens":
            context.status_code = 201
            context.headers["X-Subject-Token"] = uuid.uuid4().hex
            root = getattr(self._local, "root", None)
            return self.fixture.v3_token if root is None else self._served_token(root)
        if path == "/":
            return {"versions": {"values": [{"id": "v3.14", "status": "stable", "links": [
                {"href": self._href("identity", "/v3/"), "rel": "self"}]}]}}
        raise ApiError(404, f"identity {path} not found")

    def _href(self, service: str, suffix: str) -> str:
        """A service URL as the client reached the fake: served (root/service) or in-process."""
        root = getattr(self._local, "root", None)
        return f"{root}/{service}{suffix}" if root else f"https://{service}.example.com{suffix}"

    def _served_token(self, root: str) -> dict:
        """A Keystone v3 token like ConnectionFixture's (same project), with a catalog of the four
        services this fake serves under `root`, fresh (its expiry an hour from now) every time."""
        from keystoneauth1.fixture import v3

        token = v3.Token(project_id=self.project_id)
        for service, name, suffix in (("identity", "keystone", ""), ("compute", "nova", "/v2.1/"),
                                      ("network", "neutron", ""), ("image", "glance", "")):
            url = f"{root}/{service}{suffix}"
            token.add_service(service, name=name).add_standard_endpoints(
                public=url, internal=url, admin=url, region="RegionOne")
        return token

    # -- Nova -----------------------------------------------------------------------------------
    def _compute(self, method, path, query, body, context):
        parts = path.removeprefix("/v2.1").strip("/").split("/")
        if parts == [""]:
            return {"version": {"id": "v2.1", "status": "CURRENT", "version": "2.90", "min_version": "2.1",
                                "links": [{"href": self._href("compute", "/v2.1/"), "rel": "self"}]}}
        head = parts[0]
        if head == "servers":
            return self._servers(method, parts[1:], query, body, context)
        if head == "flavors":
            if parts[1:] == ["detail"]:
                return {"flavors": list(self.flavors.values())}
            return {"flavor": self._get(self.flavors, parts[1], "flavor")}
        if head == "os-keypairs":
            if method == "POST":
                kp = body["keypair"]
                if kp["name"] in self.keypairs:
                    raise ApiError(409, f"Key pair '{kp['name']}' already exists.")
                self.keypairs[kp["name"]] = {"name": kp["name"], "public_key": kp["public_key"], "type": "ssh",
                                             "fingerprint": "fake:" + uuid.uuid4().hex[:16], "user_id": "u"}
                return {"keypair": self.keypairs[kp["name"]]}
            if len(parts) == 1:
                return {"keypairs": [{"keypair": kp} for kp in self.keypairs.values()]}
            kp = self._get(self.keypairs, parts[1], "keypair")
            if method == "DELETE":
                del self.keypairs[kp["name"]]
                context.status_code = 202
                return None
            return {"keypair": kp}
        if head == "limits":
            used = self.compute_usage()
            return {"limits": {"rate": [], "absolute": {
                "maxTotalInstances": self.max_instances, "totalInstancesUsed": used["instances"],
                "maxTotalCores": self.max_cores, "totalCoresUsed": used["cores"],
                "maxTotalRAMSize": self.max_ram, "totalRAMUsed": used["ram"]}}}
        if head == "os-availability-zone":
            return {"availabilityZoneInfo": [{"zoneName": z, "zoneState": {"available": True}, "hosts": None}
                                             for z in ("az1", "az2", "az3")]}
        raise ApiError(404, f"compute {path} not found")

    def _servers(self, method, parts, query, body, context):
        if method == "POST" and not parts:
            context.status_code = 202
            return {"server": self._create_server(body["server"])}
        if parts in ([], ["detail"]):
            found = [s for s in self.servers.values()
                     if "name" not in query or re.search(query["name"][0], s["name"])]
            return {"servers": [self._show_server(s) for s in found]}
        server = self._get(self.servers, parts[0], "server")
        if method == "DELETE":
            if self.boot is None:
                self._delete_server(server)
            else:  # Nova answers at once and deletes in the background; GET shows it until then
                self._in_background(server, "deleting", self._boot_delete)
            context.status_code = 204
            return None
        if parts[1:] == ["action"]:
            return self._server_action(server, body, context)
        return {"server": self._show_server(server)}

    def compute_usage(self) -> dict[str, int]:
        """What the project's servers take of its compute quotas (any status but deleted, as Nova counts)."""
        flavors = [self.flavors.get(s["flavor"]["id"], {}) for s in self.servers.values()]
        return {"instances": len(flavors), "cores": sum(f.get("vcpus", 0) for f in flavors),
                "ram": sum(f.get("ram", 0) for f in flavors)}

    def _create_server(self, req: dict) -> dict:
        if len(self.servers) >= self.max_instances:
            raise ApiError(403, f"Quota exceeded for instances: Requested 1, but already used "
                                f"{len(self.servers)} of {self.max_instances} instances", "Forbidden")
        flavor = self.flavors.get(req.get("flavorRef", ""))
        used = self.compute_usage()
        for what, size, limit in (("cores", "vcpus", self.max_cores), ("ram", "ram", self.max_ram)):
            if flavor is not None and used[what] + flavor[size] > limit:
                raise ApiError(403, f"Quota exceeded for {what}: Requested {flavor[size]}, but already used "
                                    f"{used[what]} of {limit} {what}", "Forbidden")
        if req.get("imageRef", "") not in self.images:  # Nova's words, naming no image (not Glance's 404)
            raise ApiError(400, "Can not find requested image", "badRequest")
        self._get(self.flavors, req.get("flavorRef", ""), "flavor")
        if req.get("key_name") and req["key_name"] not in self.keypairs:
            raise ApiError(400, "Invalid key_name provided.")
        user_data = req.get("user_data") or ""
        if len(user_data) > MAX_USER_DATA_B64:
            raise ApiError(400, "User data too large. User data must be no larger than 65535 bytes once base64 encoded.")
        base64.b64decode(user_data, validate=True)
        ports = []
        for net in req.get("networks") or []:
            port = self._get(self.ports, net.get("port", ""), "port")
            if port["device_id"]:
                raise ApiError(409, f"Port {port['id']} is still in use.")
            ports.append(port)
        server = {"id": new_id(), "name": req["name"], "status": "BUILD", "metadata": req.get("metadata") or {},
                  "OS-EXT-AZ:availability_zone": req.get("availability_zone") or "nova",
                  "image": {"id": req["imageRef"]}, "flavor": {"id": req["flavorRef"]},
                  "key_name": req.get("key_name"), "config_drive": "True" if req.get("config_drive") else "",
                  "user_data": user_data, "created": now(), "updated": now(), "tenant_id": self.project_id,
                  "user_id": "u", "hostId": "", "addresses": {}, "links": [], "console": "",
                  "OS-EXT-STS:task_state": None}
        for port in ports:
            port.update(device_id=server["id"], device_owner=f"compute:{server['OS-EXT-AZ:availability_zone']}")
        self.servers[server["id"]] = server
        if self.boot is not None and server["OS-EXT-AZ:availability_zone"] not in self.no_capacity | self.build_fails:
            self._in_background(server, "spawning", self._boot_server)
        return {"id": server["id"], "links": [], "adminPass": "x", "OS-DCF:diskConfig": "MANUAL",
                "security_groups": [{"name": "default"}]}

    def _show_server(self, server: dict) -> dict:
        if server["status"] == "BUILD":  # the scheduler decides on the first look
            if server["OS-EXT-AZ:availability_zone"] in self.no_capacity:
                server.update(status="ERROR", fault={"code": 500, "message": NO_VALID_HOST, "created": now()})
            elif server["OS-EXT-AZ:availability_zone"] in self.build_fails:
                server.update(status="ERROR", fault={"code": 500, "message": BUILD_FAILED.format(id=server["id"]),
                                                     "created": now()})
            elif self.boot is None:  # booting: ACTIVE once the container runs (_boot_server)
                server["status"] = "ACTIVE"
                server["console"] = (
                    f"Cloud-init v. 22.4 running 'modules:final'\n-----BEGIN SSH HOST KEY FINGERPRINTS-----\n"
                    f"256 SHA256:{base64.b64encode(os.urandom(32)).decode().rstrip('=')} root@{server['name']} (ED25519)\n"
                    f"-----END SSH HOST KEY FINGERPRINTS-----\n")
        elif (self.boot is not None and server["status"] == "ACTIVE" and not server["OS-EXT-STS:task_state"]
              and self.boot.has(server["id"]) and self.boot.state(server["id"]) != "running"):
            server.update(status="SHUTOFF", updated=now())  # powered off from inside (Nova's power-state sync)
        shown = {k: v for k, v in server.items() if k not in ("user_data", "console")}
        addresses: dict[str, list] = {}
        for port in self.ports.values():
            if port["device_id"] != server["id"]:
                continue
            net = self.networks[port["network_id"]]["name"]
            for ip in port["fixed_ips"]:
                addresses.setdefault(net, []).append({"addr": ip["ip_address"], "version": 4, "OS-EXT-IPS:type": "fixed"})
            for fip in self.fips.values():
                if fip["port_id"] == port["id"]:
                    addresses[net].append({"addr": fip["floating_ip_address"], "version": 4, "OS-EXT-IPS:type": "floating"})
        shown["addresses"] = addresses
        return shown

    def _delete_server(self, server: dict) -> None:
        del self.servers[server["id"]]
        for port in self.ports.values():  # ports the user created survive (preserve_on_delete)
            if port["device_id"] == server["id"]:
                port.update(device_id="", device_owner="")

    def _server_action(self, server, body, context):
        if "os-getConsoleOutput" in body:
            if self.boot is None:
                return {"output": server["console"]}
            return {"output": self._boot_console(server, (body["os-getConsoleOutput"] or {}).get("length"))}
        if "os-start" in body or "os-stop" in body:
            if server["status"] != ("SHUTOFF" if "os-start" in body else "ACTIVE") or server["OS-EXT-STS:task_state"]:
                raise ApiError(409, f"Cannot '{next(iter(body))}' instance {server['id']} while it is {server['status']}")
            if self.boot is None:
                server["status"] = "ACTIVE" if "os-start" in body else "SHUTOFF"
            elif "os-stop" in body:
                self._in_background(server, "powering-off", self._boot_power, False)
            else:
                self._in_background(server, "powering-on", self._boot_power, True)
            context.status_code = 202
            return None
        if "createImage" in body:
            req = body["createImage"]
            image = self.add_image(req["name"], visibility="private", **(req.get("metadata") or {}))
            image["status"] = "active"
            if self.boot is not None:  # saving until the container is committed
                if server["id"] not in self._threads and not self.boot.has(server["id"]):
                    del self.images[image["id"]]
                    raise ApiError(409, f"Cannot 'createImage' instance {server['id']}: it has no disk yet")
                image.update(status="queued", size=None)
                self._in_background(server, "image_snapshot", self._boot_capture, image)
            context.status_code = 202
            return {"image_id": image["id"]}
        raise ApiError(400, f"unsupported action {list(body)}")

    # -- booting (self.boot set) ----------------------------------------------------------------
    def _in_background(self, server: dict, task: str, work, *args) -> None:
        """Run work(server_id, *args) in a thread of the server's own (one task at a time, as
        Nova's task_state), the server showing `task` until it is done."""
        server["OS-EXT-STS:task_state"] = task
        before = self._threads.get(server["id"])

        def run() -> None:
            if before is not None:
                before.join()
            try:
                work(server["id"], *args)
            except Exception as exc:  # noqa: BLE001 - the server records what went wrong
                with self.lock:
                    if server["id"] in self.servers:
                        server.update(status="ERROR", fault={"code": 500, "message": f"{task}: {exc}", "created": now()})
            finally:
                with self.lock:
                    server["OS-EXT-STS:task_state"] = None
                    if self._threads.get(server["id"]) is threading.current_thread():
                        del self._threads[server["id"]]

        thread = threading.Thread(target=run, name=f"fake-nova-{task}-{server['id'][:8]}", daemon=True)
        self._threads[server["id"]] = thread
        thread.start()

    def wait_idle(self, timeout: float = 60.0) -> bool:
        """Wait for the servers' background tasks (boot, stop, capture, delete) to end; False
        when some still run after `timeout` seconds."""
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                threads = list(getattr(self, "_threads", {}).values())
            if not threads:
                return True
            for t in threads:
                t.join(max(0.0, deadline - time.monotonic()))
            if time.monotonic() >= deadline:
                with self.lock:
                    return not any(t.is_alive() for t in getattr(self, "_threads", {}).values())

    def _boot_server(self, server_id: str) -> None:
        with self.lock:
            server = self.servers[server_id]
            image_id = server["image"]["id"]
            if image_id not in self.docker_images:
                raise RuntimeError(f"image {image_id} ({self.images.get(image_id, {}).get('name')}) has no disk in "
                                   f"this fake: boot from {BOOT_IMAGE} or a snapshot")
            image = self.docker_images[image_id]
            keys = [self.keypairs[server["key_name"]]["public_key"]] if server.get("key_name") in self.keypairs else []
            user_data = base64.b64decode(server["user_data"] or "")
            networks = self._wanted_networks(server_id)
        self.boot.boot(server_id, server["name"], image, user_data, list(networks.items()), keys, self.vendor_data)
        with self.lock:
            self._rewire(server_id)  # floating IPs associated while the container was created
            server.update(status="ACTIVE", updated=now())

    def _wanted_networks(self, server_id: str) -> dict[str, str]:
        """The server's interfaces as Neutron has them: docker network -> address (fixed IPs
        first, then floating IPs). Creates the Docker networks of subnets seen first here."""
        wanted: dict[str, str] = {}
        for port in self.ports.values():
            if port["device_id"] != server_id:
                continue
            for ip in port["fixed_ips"]:
                subnet = self.subnets[ip["subnet_id"]]
                if subnet["id"] not in self._subnet_nets:
                    net = self.networks.get(subnet["network_id"], {})
                    self._subnet_nets[subnet["id"]] = self.boot.ensure_network(
                        f"{net.get('name') or 'net'}-{subnet['id'][:8]}", subnet["cidr"], subnet.get("gateway_ip"))
                wanted[self._subnet_nets[subnet["id"]]] = ip["ip_address"]
        for fip in self.fips.values():
            port = self.ports.get(fip["port_id"] or "")
            if port is not None and port["device_id"] == server_id:
                wanted[self.fip_network] = fip["floating_ip_address"]
        return wanted

    def _rewire(self, server_id: str | None = None) -> None:
        """Make the containers' interfaces what Neutron says (a floating IP associated, moved or
        released; a port deleted); drop the Docker networks of deleted subnets."""
        for sid in [server_id] if server_id else list(self.servers):
            if not self.boot.has(sid):
                continue  # not created yet: _boot_server wires it once it is
            wanted, have = self._wanted_networks(sid), self.boot.attachments(sid)
            for net in have.keys() - wanted.keys():
                self.boot.detach(sid, net)
            for net, ip in wanted.items():
                if have.get(net) != ip:
                    self.boot.attach(sid, net, ip)
        for subnet_id in [s for s in self._subnet_nets if s not in self.subnets]:
            name = self._subnet_nets.pop(subnet_id)
            try:
                self.boot.networks[name].remove()
                self.boot.networks.pop(name, None)
            except Exception:  # noqa: BLE001 - still in use: the run's cleanup removes it
                pass

    def _boot_console(self, server: dict, length: int | str | None) -> str:
        if not self.boot.has(server["id"]):
            return ""
        text = self.boot.console(server["id"]).replace("\r\n", "\n")
        if length is not None and int(length) >= 0:
            text = "".join(text.splitlines(keepends=True)[-int(length):]) if int(length) else ""
        return text

    def _boot_power(self, server_id: str, on: bool) -> None:
        (self.boot.start if on else self.boot.stop)(server_id)
        with self.lock:
            self.servers[server_id].update(status="ACTIVE" if on else "SHUTOFF", updated=now())

    def _boot_capture(self, server_id: str, image: dict) -> None:
        with self.lock:
            image["status"] = "saving"
        try:
            ref = self.boot.capture(server_id, image["name"])
        except Exception:
            with self.lock:
                image["status"] = "killed"
            raise
        with self.lock:
            size = self.boot.client.images.get(ref).attrs.get("Size")
            self.docker_images[image["id"]] = ref
            image.update(status="active", size=size, updated_at=now())

    def _boot_delete(self, server_id: str) -> None:
        self.boot.delete(server_id)
        with self.lock:
            server = self.servers.get(server_id)
            if server is not None:
                self._delete_server(server)

    # -- Glance ---------------------------------------------------------------------------------
    def _image(self, method, path, query, body, context):
        if path == "/":
            return {"versions": [{"id": "v2.15", "status": "CURRENT", "links": [
                {"href": self._href("image", "/v2/"), "rel": "self"}]}]}
        parts = path.removeprefix("/v2").strip("/").split("/")
        if parts == ["images"]:
            found = [i for i in self.images.values()
                     if all(i.get(k) == v[0] for k, v in query.items() if k in ("name", "visibility", "owner", "status"))
                     and all(t in i["tags"] for t in query.get("tag", []))]
            return {"images": found, "first": "/v2/images", "schema": "/v2/schemas/images"}
        image = self._get(self.images, parts[1], "image")
        if parts[2:3] == ["tags"]:
            if method == "PUT" and parts[3] not in image["tags"]:
                image["tags"].append(parts[3])
            elif method == "DELETE" and parts[3] in image["tags"]:
                image["tags"].remove(parts[3])
            context.status_code = 204
            return None
        if method == "DELETE":
            del self.images[image["id"]]
            if self.boot is not None and image["id"] in self.docker_images:
                ref = self.docker_images.pop(image["id"])
                if ref in self.boot.images:  # captured by this run: the disk goes with the image
                    self.boot.remove_image(ref)
            context.status_code = 204
            return None
        return image

    # -- shared ---------------------------------------------------------------------------------
    @staticmethod
    def _get(store: dict, key: str, what: str) -> dict:
        if key in store:
            return store[key]
        raise ApiError(404, f"{what.replace('_', ' ').capitalize()} {key} could not be found.",
                       "itemNotFound" if what in ("server", "flavor", "keypair") else f"{what.title().replace('_', '')}NotFound")

    def clouds_yaml(self, directory: Path, cloud: str) -> Path:
        """A clouds.yaml for openstack.connect(cloud=...), pointing at the fake Keystone."""
        path = directory / "clouds.yaml"
        path.write_text(json.dumps({"clouds": {cloud: {
            "auth": {"auth_url": "https://identity.example.com", "username": "admin", "password": "password",
                     "project_name": "admin", "user_domain_name": "default", "project_domain_name": "default"},
            "region_name": "RegionOne", "identity_api_version": "3"}}}))
        return path
