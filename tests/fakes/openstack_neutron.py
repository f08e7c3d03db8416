"""Neutron of the in-memory OpenStack (openstack_cloud.py): networks, subnets, routers, ports,
floating IPs, security groups, tags, and the dependencies Neutron enforces on delete."""

from __future__ import annotations

import ipaddress
import time
import uuid


class ApiError(Exception):
    """An API refusal: the HTTP status and the fault the service puts in its body."""

    def __init__(self, status: int, message: str, kind: str = "") -> None:
        super().__init__(message)
        self.status, self.message, self.kind = status, message, kind or {
            400: "BadRequest", 403: "Forbidden", 404: "NotFound", 409: "Conflict", 413: "OverLimit"}.get(status, "Error")


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def new_id() -> str:
    return str(uuid.uuid4())


class NeutronApi:
    """Mixed into FakeOpenStack, which holds the stores (self.networks, self.ports...)."""

    # Tags in a POST body need Neutron's `tag-creation` extension (2023.1 on). Zed's Neutron (Debian
    # 12, scripts/openstack.sh) refuses them with this 400, except on a port, whose POST it accepts
    # and whose tags it drops: False plays that Neutron.
    tag_creation = True

    # -- requests --------------------------------------------------------------------------------
    def _network(self, method, path, query, body, context):
        if path == "/":
            return {"versions": [{"id": "v2.0", "status": "CURRENT", "links": [
                {"href": self._href("network", "/v2.0/"), "rel": "self"}]}]}
        parts = path.removeprefix("/v2.0").strip("/").split("/")
        kind = parts[0]
        if kind == "quotas" and method == "GET" and len(parts) in (2, 3):
            return self._quota(parts[1], details=parts[2:] == ["details"])
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
                if not self.tag_creation and "tags" in body[singular]:
                    if kind != "ports":
                        raise ApiError(400, "Attribute 'tags' not allowed in POST")
                    body[singular] = {k: v for k, v in body[singular].items() if k != "tags"}
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

    def _quota(self, project: str, details: bool) -> dict:
        """The project's Neutron quotas: the floating IPs' from max_fips and what exists, the rest
        unlimited (-1); with details, the usage too."""
        if project != self.project_id:
            raise ApiError(404, f"Project {project} could not be found.")
        fips = {"limit": self.max_fips, "used": len(self.fips), "reserved": 0}
        if details:
            return {"quota": {"floatingip": fips}}
        return {"quota": {"floatingip": self.max_fips, "project_id": project}}

    def _create_fips(self, req: dict) -> dict:
        if len(self.fips) >= self.max_fips:
            raise ApiError(409, "Quota exceeded for resources: ['floatingip'].", "OverQuota")
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
        rule = {"id": new_id(), "protocol": None, "port_range_min": None, "port_range_max": None,
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

