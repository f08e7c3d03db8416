"""A small in-memory OpenStack (Keystone, Nova, Neutron, Glance) behind requests-mock.

openstacksdk runs unmodified against it: it authenticates against the Keystone catalog that
openstacksdk's own `openstack.fixture.connection.ConnectionFixture` builds (compute at
https://compute.example.com/v2.1/, network at https://network.example.com, image at
https://image.example.com), discovers versions, negotiates microversions and builds and parses
every request itself. The fake keeps just enough of each API to be honest about what a real cloud
refuses: a fixed IP used twice, a router with interfaces, a subnet or network still in use, quota,
user-data over Nova's limit, and servers the scheduler cannot place ("No valid host was found").

Knobs for tests: `throttle(fraction)` (429/503 before the fake), `delay(seconds)`, `no_capacity`
zones, `max_instances`, `fail_fip_for` robots, `fail_next` operations; `calls` counts (METHOD, path template).
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
from urllib.parse import parse_qs, urlparse

import requests_mock
from openstack.fixture.connection import ConnectionFixture

from .openstack_neutron import ApiError, NeutronApi, new_id, now

NO_VALID_HOST = "No valid host was found. There are not enough hosts available."
MAX_USER_DATA_B64 = 65_535  # Nova's limit on the base64 text
FIP_POOL = ipaddress.IPv4Network("203.0.113.0/24")  # TEST-NET-3: never contacted
HOSTS = ("identity", "compute", "network", "image")


# Path segments that name one resource: after these collections, or anything that is a UUID.
_NAMED = {"servers", "flavors", "os-keypairs", "images", "tags", "networks", "subnets", "routers", "ports",
          "floatingips", "security-groups", "security-group-rules"}


def _template(path: str) -> str:
    """/v2.1/servers/<uuid>/action -> /v2.1/servers/{id}/action (the operation, for counting)."""
    parts = path.split("/")
    out = [p if i == 0 or (parts[i - 1] not in _NAMED and not re.fullmatch(r"[0-9a-f-]{36}", p))
           or p == "detail" else "{id}" for i, p in enumerate(parts)]
    return "/".join(out)


class FakeOpenStack(NeutronApi):
    def __init__(self) -> None:
        self.fixture = ConnectionFixture()  # openstacksdk's own catalog + token
        self.project_id = self.fixture.project_id
        self.lock = threading.RLock()
        self.calls: Counter = Counter()
        self.throttle_fraction = 0.0
        self._n = 0
        self.delay_s = 0.0
        self.no_capacity: set[str] = set()  # zones where the scheduler finds no host
        self.max_instances = 100
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
        self._fip_hosts = iter(FIP_POOL.hosts())
        self.adapter = self._routes()
        ext = self.add("networks", {"name": "public", "router:external": True})
        self.add("subnets", {"network_id": ext["id"], "cidr": str(FIP_POOL), "name": "public-v4"})
        self.add_flavor("m1.small")
        self.add_image("ubuntu-20.04")

    # -- seeding --------------------------------------------------------------------------------
    def add(self, collection: str, body: dict) -> dict:
        """A Neutron-style resource with the defaults the API fills in."""
        res = {"id": new_id(), "name": "", "tags": [], "project_id": self.project_id,
               "tenant_id": self.project_id, "description": "", "created_at": now(), **body}
        if collection == "networks":
            res.setdefault("router:external", False)
            res.setdefault("subnets", [])
            res.setdefault("status", "ACTIVE")
        getattr(self, collection)[res["id"]] = res
        return res

    def add_flavor(self, name: str) -> dict:
        flavor = {"id": new_id(), "name": name, "vcpus": 2, "ram": 4096, "disk": 20,
                  "os-flavor-access:is_public": True, "OS-FLV-EXT-DATA:ephemeral": 0, "swap": 0}
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
        host = urlparse(request.url).hostname.split(".")[0]
        path = request.path.rstrip("/") or "/"
        query = {k: v for k, v in parse_qs(urlparse(request.url).query, keep_blank_values=True).items()}
        template = _template(path)
        op = (request.method, f"{host}:{template}")
        if self.delay_s:
            time.sleep(self.delay_s)  # outside the lock: concurrent callers overlap as on a real cloud
        context.headers["Content-Type"] = "application/json"
        with self.lock:
            self.calls[op] += 1
            if host != "identity" and self._throttled():
                context.status_code = 429 if self._n % 2 else 503
                context.headers["Retry-After"] = "0"
                return {"message": "Rate limit exceeded" if context.status_code == 429 else "Service Unavailable"}
            body = request.json() if request.body else {}
            try:
                if op in self.fail_next:
                    raise ApiError(*self.fail_next.pop(op))
                return getattr(self, f"_{host}")(request.method, path, query, body, context)
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
        if method == "POST" and path == "/v3/auth/tokens":
            context.status_code = 201
            context.headers["X-Subject-Token"] = uuid.uuid4().hex
            return self.fixture.v3_token
        if path == "/":
            return {"versions": {"values": [{"id": "v3.14", "status": "stable", "links": [
                {"href": "https://identity.example.com/v3/", "rel": "self"}]}]}}
        raise ApiError(404, f"identity {path} not found")

    # -- Nova -----------------------------------------------------------------------------------
    def _compute(self, method, path, query, body, context):
        parts = path.removeprefix("/v2.1").strip("/").split("/")
        if parts == [""]:
            return {"version": {"id": "v2.1", "status": "CURRENT", "version": "2.90", "min_version": "2.1",
                                "links": [{"href": "https://compute.example.com/v2.1/", "rel": "self"}]}}
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
            used = len(self.servers)
            return {"limits": {"rate": [], "absolute": {
                "maxTotalInstances": self.max_instances, "totalInstancesUsed": used,
                "maxTotalCores": 2 * self.max_instances, "totalCoresUsed": 2 * used,
                "maxTotalRAMSize": 4096 * self.max_instances, "totalRAMUsed": 4096 * used}}}
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
            self._delete_server(server)
            context.status_code = 204
            return None
        if parts[1:] == ["action"]:
            return self._server_action(server, body, context)
        return {"server": self._show_server(server)}

    def _create_server(self, req: dict) -> dict:
        if len(self.servers) >= self.max_instances:
            raise ApiError(403, f"Quota exceeded for instances: Requested 1, but already used "
                                f"{len(self.servers)} of {self.max_instances} instances", "Forbidden")
        self._get(self.images, req.get("imageRef", ""), "image")
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
                  "user_id": "u", "hostId": "", "addresses": {}, "links": [], "console": ""}
        for port in ports:
            port.update(device_id=server["id"], device_owner=f"compute:{server['OS-EXT-AZ:availability_zone']}")
        self.servers[server["id"]] = server
        return {"id": server["id"], "links": [], "adminPass": "x", "OS-DCF:diskConfig": "MANUAL",
                "security_groups": [{"name": "default"}]}

    def _show_server(self, server: dict) -> dict:
        if server["status"] == "BUILD":  # the scheduler decides on the first look
            if server["OS-EXT-AZ:availability_zone"] in self.no_capacity:
                server.update(status="ERROR", fault={"code": 500, "message": NO_VALID_HOST, "created": now()})
            else:
                server["status"] = "ACTIVE"
                server["console"] = (
                    f"Cloud-init v. 22.4 running 'modules:final'\n-----BEGIN SSH HOST KEY FINGERPRINTS-----\n"
                    f"256 SHA256:{base64.b64encode(os.urandom(32)).decode().rstrip('=')} root@{server['name']} (ED25519)\n"
                    f"-----END SSH HOST KEY FINGERPRINTS-----\n")
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
            return {"output": server["console"]}
        if "os-start" in body or "os-stop" in body:
            if server["status"] != ("SHUTOFF" if "os-start" in body else "ACTIVE"):
                raise ApiError(409, f"Cannot '{next(iter(body))}' instance {server['id']} while it is {server['status']}")
            server["status"] = "ACTIVE" if "os-start" in body else "SHUTOFF"
            context.status_code = 202
            return None
        if "createImage" in body:
            req = body["createImage"]
            image = self.add_image(req["name"], visibility="private", **(req.get("metadata") or {}))
            image["status"] = "active"
            context.status_code = 202
            return {"image_id": image["id"]}
        raise ApiError(400, f"unsupported action {list(body)}")

    # -- Glance ---------------------------------------------------------------------------------
    def _image(self, method, path, query, body, context):
        if path == "/":
            return {"versions": [{"id": "v2.15", "status": "CURRENT", "links": [
                {"href": "https://image.example.com/v2/", "rel": "self"}]}]}
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
