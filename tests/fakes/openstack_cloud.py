"""A small in-memory OpenStack (Keystone, Nova, Neutron, Glance) behind requests-mock.

openstacksdk runs unmodified against it: it authenticates against the Keystone catalog that
openstacksdk's own `openstack.fixture.connection.ConnectionFixture` builds (compute at
https://compute.example.com/v2.1/, network at https://network.example.com, image at
https://image.example.com), discovers versions, negotiates microversions and builds and parses
every request itself. The fake keeps just enough of each API to be honest about what a real cloud
refuses: a fixed IP used twice, a router with interfaces, a subnet or network still in use, quota,
user-data over Nova's limit, and servers the scheduler cannot place ("No valid host was found").

Knobs for tests: `throttle(fraction)` (429/503 before the fake), `delay(seconds)`, `no_capacity`
zones, `max_instances`, `fail_fip_for` robots; `calls` counts (METHOD, path template).
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

NO_VALID_HOST = "No valid host was found. There are not enough hosts available."
MAX_USER_DATA_B64 = 65_535  # Nova's limit on the base64 text
FIP_POOL = ipaddress.IPv4Network("203.0.113.0/24")  # TEST-NET-3: never contacted
HOSTS = ("identity", "compute", "network", "image")


class ApiError(Exception):
    def __init__(self, status: int, message: str, kind: str = "") -> None:
        super().__init__(message)
        self.status, self.message, self.kind = status, message, kind or {
            400: "BadRequest", 403: "Forbidden", 404: "NotFound", 409: "Conflict", 413: "OverLimit"}.get(status, "Error")


# Path segments that name one resource: after these collections, or anything that is a UUID.
_NAMED = {"servers", "flavors", "os-keypairs", "images", "tags", "networks", "subnets", "routers", "ports",
          "floatingips", "security-groups", "security-group-rules"}


def _template(path: str) -> str:
    """/v2.1/servers/<uuid>/action -> /v2.1/servers/{id}/action (the operation, for counting)."""
    parts = path.split("/")
    out = [p if i == 0 or (parts[i - 1] not in _NAMED and not re.fullmatch(r"[0-9a-f-]{36}", p))
           or p == "detail" else "{id}" for i, p in enumerate(parts)]
    return "/".join(out)


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _new_id() -> str:
    return str(uuid.uuid4())


class FakeOpenStack:
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
        ext = self.add("networks", {"name": "public", "router:external": True})
        self.add("subnets", {"network_id": ext["id"], "cidr": str(FIP_POOL), "name": "public-v4"})
        self.add_flavor("m1.small")
        self.add_image("ubuntu-20.04")

    # -- seeding --------------------------------------------------------------------------------
    def add(self, collection: str, body: dict) -> dict:
        """A Neutron-style resource with the defaults the API fills in."""
        res = {"id": _new_id(), "name": "", "tags": [], "project_id": self.project_id,
               "tenant_id": self.project_id, "description": "", "created_at": _now(), **body}
        if collection == "networks":
            res.setdefault("router:external", False)
            res.setdefault("subnets", [])
            res.setdefault("status", "ACTIVE")
        getattr(self, collection)[res["id"]] = res
        return res

    def add_flavor(self, name: str) -> dict:
        flavor = {"id": _new_id(), "name": name, "vcpus": 2, "ram": 4096, "disk": 20,
                  "os-flavor-access:is_public": True, "OS-FLV-EXT-DATA:ephemeral": 0, "swap": 0}
        self.flavors[flavor["id"]] = flavor
        return flavor

    def add_image(self, name: str, **props) -> dict:
        image = {"id": _new_id(), "name": name, "status": "active", "visibility": "public", "tags": [],
                 "created_at": _now(), "updated_at": _now(), "size": 2_000_000_000, "owner": self.project_id,
                 "disk_format": "qcow2", "container_format": "bare", **props}
        self.images[image["id"]] = image
        return image

    # -- requests-mock wiring -------------------------------------------------------------------
    def install(self, mocker: requests_mock.Mocker) -> None:
        for host in HOSTS:
            mocker.register_uri(requests_mock.ANY, re.compile(rf"https://{host}\.example\.com(/|$)"),
                                json=self._respond)

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
            raise ApiError(400, f"Invalid key_name provided.")
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
        server = {"id": _new_id(), "name": req["name"], "status": "BUILD", "metadata": req.get("metadata") or {},
                  "OS-EXT-AZ:availability_zone": req.get("availability_zone") or "nova",
                  "image": {"id": req["imageRef"]}, "flavor": {"id": req["flavorRef"]},
                  "key_name": req.get("key_name"), "config_drive": "True" if req.get("config_drive") else "",
                  "user_data": user_data, "created": _now(), "updated": _now(), "tenant_id": self.project_id,
                  "user_id": "u", "hostId": "", "addresses": {}, "links": [], "console": ""}
        for port in ports:
            port.update(device_id=server["id"], device_owner=f"compute:{server['OS-EXT-AZ:availability_zone']}")
        self.servers[server["id"]] = server
        return {"id": server["id"], "links": [], "adminPass": "x", "OS-DCF:diskConfig": "MANUAL",
                "security_groups": [{"name": "default"}]}

    def _show_server(self, server: dict) -> dict:
        if server["status"] == "BUILD":  # the scheduler decides on the first look
            if server["OS-EXT-AZ:availability_zone"] in self.no_capacity:
                server.update(status="ERROR", fault={"code": 500, "message": NO_VALID_HOST, "created": _now()})
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

    # -- Neutron --------------------------------------------------------------------------------
    def _network(self, method, path, query, body, context):
        if path == "/":
            return {"versions": [{"id": "v2.0", "status": "CURRENT", "links": [
                {"href": "https://network.example.com/v2.0/", "rel": "self"}]}]}
        parts = path.removeprefix("/v2.0").strip("/").split("/")
        kind = parts[0]
        collection = {"networks": "networks", "subnets": "subnets", "routers": "routers", "ports": "ports",
                      "floatingips": "fips", "security-groups": "sgs", "security-group-rules": None}.get(kind, "")
        if collection == "":
            raise ApiError(404, f"network {path} not found")
        singular = {"floatingips": "floatingip", "security-groups": "security_group",
                    "security-group-rules": "security_group_rule"}.get(kind, kind[:-1])
        if collection is None:
            return self._sg_rules(method, parts[1:], query, body, context)
        store = getattr(self, collection)
        if not parts[1:]:
            if method == "POST":
                context.status_code = 201
                return {singular: getattr(self, f"_create_{collection}")(body[singular])}
            return {kind.replace("-", "_"): [r for r in store.values() if self._matches(r, query)]}
        res = self._get(store, parts[1], singular)
        if parts[2:] == ["tags"] and method == "PUT":
            res["tags"] = list(body["tags"])
            return {"tags": res["tags"]}
        if parts[2:] in (["add_router_interface"], ["remove_router_interface"]):
            return self._router_interface(res, parts[2], body)
        if method == "DELETE":
            getattr(self, f"_check_delete_{collection}", lambda r: None)(res)
            del store[res["id"]]
            context.status_code = 204
            return None
        if method == "PUT":
            res.update(body[singular])
        return {singular: res}

    @staticmethod
    def _matches(res: dict, query: dict) -> bool:
        for key, values in query.items():
            if key in ("fields", "limit", "marker", "sort_key", "sort_dir"):
                continue
            if key == "tags":
                wanted = {t for v in values for t in v.split(",")}
                if not wanted <= set(res.get("tags", [])):
                    return False
                continue
            have = res.get(key)
            if str(have).lower() not in {v.lower() for v in values}:
                return False
        return True

    def _create_networks(self, req: dict) -> dict:
        return self.add("networks", {**req, "router:external": False})

    def _create_subnets(self, req: dict) -> dict:
        net = self._get(self.networks, req["network_id"], "network")
        cidr = ipaddress.IPv4Network(req["cidr"])
        gateway = req.get("gateway_ip") or str(next(cidr.hosts()))
        subnet = self.add("subnets", {**req, "cidr": str(cidr), "gateway_ip": gateway, "ip_version": 4})
        net["subnets"].append(subnet["id"])
        return subnet

    def _create_routers(self, req: dict) -> dict:
        gw = req.get("external_gateway_info")
        if gw:
            ext = self._get(self.networks, gw["network_id"], "network")
            if not ext["router:external"]:
                raise ApiError(400, f"Network {ext['id']} is not an external network")
        return self.add("routers", {**req, "status": "ACTIVE", "interfaces": []})

    def _router_interface(self, router: dict, action: str, req: dict) -> dict:
        subnet = self._get(self.subnets, req["subnet_id"], "subnet")
        if action == "add_router_interface":
            if subnet["id"] in router["interfaces"]:
                raise ApiError(400, f"Router already has a port on subnet {subnet['id']}")
            port = self.add("ports", {"network_id": subnet["network_id"], "device_id": router["id"],
                                      "device_owner": "network:router_interface", "allowed_address_pairs": [],
                                      "fixed_ips": [{"subnet_id": subnet["id"], "ip_address": subnet["gateway_ip"]}]})
            router["interfaces"].append(subnet["id"])
        else:
            if subnet["id"] not in router["interfaces"]:
                raise ApiError(404, f"Router {router['id']} has no interface on subnet {subnet['id']}")
            router["interfaces"].remove(subnet["id"])
            port = next(p for p in self.ports.values() if p["device_id"] == router["id"]
                        and p["fixed_ips"][0]["subnet_id"] == subnet["id"])
            del self.ports[port["id"]]
        return {"id": router["id"], "subnet_id": subnet["id"], "port_id": port["id"], "tenant_id": self.project_id}

    def _create_ports(self, req: dict) -> dict:
        net = self._get(self.networks, req["network_id"], "network")
        fixed = []
        for ip in req.get("fixed_ips") or [{"subnet_id": net["subnets"][0]}]:
            subnet = self._get(self.subnets, ip["subnet_id"], "subnet")
            addr = ip.get("ip_address") or self._free_ip(subnet)
            if ipaddress.IPv4Address(addr) not in ipaddress.IPv4Network(subnet["cidr"]):
                raise ApiError(400, f"IP address {addr} is not a valid IP for the specified subnet.")
            if any(f["ip_address"] == addr for p in self.ports.values() for f in p["fixed_ips"]):
                raise ApiError(409, f"IP address {addr} already allocated in subnet {subnet['id']}",
                               "IpAddressAlreadyAllocated")
            fixed.append({"subnet_id": subnet["id"], "ip_address": addr})
        for sg in req.get("security_groups") or []:
            self._get(self.sgs, sg, "security_group")
        return self.add("ports", {"allowed_address_pairs": [], "device_id": "", "device_owner": "",
                                  "security_groups": [], "port_security_enabled": True, "status": "DOWN",
                                  **req, "fixed_ips": fixed})

    def _free_ip(self, subnet: dict) -> str:
        used = {f["ip_address"] for p in self.ports.values() for f in p["fixed_ips"]} | {subnet["gateway_ip"]}
        return str(next(h for h in ipaddress.IPv4Network(subnet["cidr"]).hosts() if str(h) not in used))

    def _create_fips(self, req: dict) -> dict:
        ext = self._get(self.networks, req["floating_network_id"], "network")
        if not ext["router:external"]:
            raise ApiError(400, f"Network {ext['id']} is not a valid external network")
        fixed = None
        if req.get("port_id"):
            port = self._get(self.ports, req["port_id"], "port")
            robot = self.servers.get(port["device_id"], {}).get("metadata", {}).get("ccrp-robot")
            if robot in self.fail_fip_for:
                self.fail_fip_for.discard(robot)
                raise ApiError(400, f"External network {ext['id']} is not reachable from subnet of port {port['id']}")
            fixed = port["fixed_ips"][0]["ip_address"]
        return self.add("fips", {"status": "DOWN", **req, "port_id": req.get("port_id"), "fixed_ip_address": fixed,
                                 "floating_ip_address": str(next(self._fip_hosts)), "router_id": None})

    def _create_sgs(self, req: dict) -> dict:
        sg = self.add("sgs", {**req, "security_group_rules": []})
        for ethertype in ("IPv4", "IPv6"):  # Neutron's default egress rules
            self._add_rule({"security_group_id": sg["id"], "direction": "egress", "ethertype": ethertype})
        return sg

    def _add_rule(self, req: dict) -> dict:
        sg = self._get(self.sgs, req["security_group_id"], "security_group")
        rule = {"id": _new_id(), "protocol": None, "port_range_min": None, "port_range_max": None,
                "remote_ip_prefix": None, "remote_group_id": None, "ethertype": "IPv4", "description": "",
                "tags": [], "project_id": self.project_id, "tenant_id": self.project_id, **req}
        key = ("direction", "ethertype", "protocol", "port_range_min", "port_range_max", "remote_ip_prefix", "remote_group_id")
        if any(all(r.get(k) == rule.get(k) for k in key) for r in sg["security_group_rules"]):
            raise ApiError(409, "Security group rule already exists.", "SecurityGroupRuleExists")
        sg["security_group_rules"].append(rule)
        return rule

    def _sg_rules(self, method, parts, query, body, context):
        if method == "POST":
            context.status_code = 201
            return {"security_group_rule": self._add_rule(body["security_group_rule"])}
        rules = [r for sg in self.sgs.values() for r in sg["security_group_rules"]]
        if not parts:
            return {"security_group_rules": [r for r in rules if self._matches(r, query)]}
        rule = next((r for r in rules if r["id"] == parts[0]), None)
        if rule is None:
            raise ApiError(404, f"Security group rule {parts[0]} could not be found.")
        if method == "DELETE":
            self.sgs[rule["security_group_id"]]["security_group_rules"].remove(rule)
            context.status_code = 204
            return None
        return {"security_group_rule": rule}

    # What Neutron refuses to delete while something still depends on it.
    def _check_delete_routers(self, router: dict) -> None:
        if router["interfaces"]:
            raise ApiError(409, f"Router {router['id']} still has ports", "RouterInUse")

    def _check_delete_subnets(self, subnet: dict) -> None:
        if any(f["subnet_id"] == subnet["id"] for p in self.ports.values() for f in p["fixed_ips"]):
            raise ApiError(409, f"Unable to complete operation on subnet {subnet['id']}: one or more ports "
                                "have an IP allocation from this subnet.", "SubnetInUse")

    def _check_delete_networks(self, net: dict) -> None:
        if any(p["network_id"] == net["id"] for p in self.ports.values()):
            raise ApiError(409, f"Unable to complete operation on network {net['id']}. There are one or more "
                                "ports still in use on the network.", "NetworkInUse")
        for subnet_id in net["subnets"]:
            self.subnets.pop(subnet_id, None)

    def _check_delete_ports(self, port: dict) -> None:
        if port["device_owner"] == "network:router_interface":
            raise ApiError(409, f"Port {port['id']} cannot be deleted directly via the port API: has device "
                                "owner network:router_interface.", "L3PortInUse")
        for fip in self.fips.values():  # Neutron disassociates floating IPs of a deleted port
            if fip["port_id"] == port["id"]:
                fip.update(port_id=None, fixed_ip_address=None)

    def _check_delete_sgs(self, sg: dict) -> None:
        if any(sg["id"] in p["security_groups"] for p in self.ports.values()):
            raise ApiError(409, f"Security Group {sg['id']} in use.", "SecurityGroupInUse")

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
