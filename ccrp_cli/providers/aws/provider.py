"""AWS provider: a clone is an EC2 instance in the fleet's common subnet with a fixed private IP
(its common-network address), source/dest check off and a route for its robot's VPN subnet, so
clones reach each other's robots through each other. In a per-clone fleet each clone holds an
Elastic IP; behind an entry gateway (the default) only the gateway does: an instance with an
interface in its public subnet (the Elastic IP's) and one at gateway_ip in the clones' subnet, whose
default route leads to that interface (network.py says why).

Every call goes through the client's api (client.py, retry.py); botocore's own retries are switched
off so that backoff lives in one place. This class is the instances' lifecycle; it composes the
client, the fleet's network (network.py), its AMIs (images.py) and what the fleet owns (owned.py).

Zones: an AWS subnet lives in one zone and each clone's private IP is fixed inside the common
subnet, so zone fallback (inventory provider.zones, in order) happens where the subnet is placed,
at bootstrap. A capacity error at launch is reported with its hint rather than moved elsewhere.
"""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ...errors import CcrpError
from ...models.inventory import Inventory
from ..base import (GATEWAY, GATEWAY_ROLE, LABEL_ROBOT, CloneRecord, CloneSpec, CloneState, Origin, OwnedResource, Quota,
                    SnapshotRecord)
from ..cloud import CloudProvider
from . import INFO, images, network, owned, tags
from .client import LIVE, AwsClient, Network
from .errors import error_code

GONE = ["shutting-down", "terminated"]
# Instance families counted by "Running On-Demand Standard (A, C, D, H, I, M, R, T, Z) instances"
# (L-1216C47A); these first letters begin other families, which have quotas of their own.
STANDARD_LETTERS = "acdhimrtz"
NOT_STANDARD = ("mac", "inf", "dl", "trn", "hpc")


def is_standard(instance_type: str) -> bool:
    family = instance_type.split(".")[0].lower()
    return family[:1] in STANDARD_LETTERS and not family.startswith(NOT_STANDARD)

# EC2's instance states in ccrp's words.
STATES = {"pending": CloneState.PENDING, "running": CloneState.RUNNING, "stopping": CloneState.STOPPING,
          "stopped": CloneState.STOPPED, "shutting-down": CloneState.DELETING, "terminated": CloneState.DELETING}


class AwsProvider(CloudProvider):
    kind = "aws"
    abilities = INFO.abilities
    images, owned = images, owned  # snapshots and owned resources: CloudProvider hands them the client

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        super().__init__(inv, workdir)
        self.client = AwsClient(inv, workdir)
        self.settings = self.client.settings
        self._service_quotas: Any = None  # its client (boto3's, untyped), made when quotas are first read

    @property
    def network(self) -> Network:
        return network.current(self.client)

    @property
    def behind(self) -> bool:
        """Whether the fleet's robots come in through its entry gateway (provider.entry: gateway)."""
        return self.settings.entry == "gateway"

    def _record(self, inst: dict, origin: Origin | None = None, public_ip: str | None = None) -> CloneRecord:
        # The gateway's common address is its second interface's (its first is in its public subnet).
        legs = {n.get("Attachment", {}).get("DeviceIndex"): n.get("PrivateIpAddress") for n in inst.get("NetworkInterfaces", [])}
        return CloneRecord(
            robot=tags.as_dict(inst).get(LABEL_ROBOT, ""), provider_id=inst["InstanceId"],
            state=CloneState.of(inst["State"]["Name"], STATES), status=inst["State"]["Name"], public_ip=public_ip or inst.get("PublicIpAddress"),
            common_ip=legs.get(1) or inst.get("PrivateIpAddress"), origin=origin,
        )

    # -- the fleet's network (network.py) ---------------------------------------------------------
    def bootstrap(self) -> None:
        network.ensure(self.client, self.operator_public_key())

    # -- snapshots (images.py) ---------------------------------------------------------------------
    def resolve_image(self, image: str) -> str:
        return images.resolve_image(self.client, image)

    # -- instances -----------------------------------------------------------------------------

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Reuse the robot's owned instance, or launch one; then converge its route and Elastic IP.
        On failure, remove only what this call created."""
        c = self.client
        net = self.network
        # One look at the robot's instances in every state: a live one is reused; the gone ones
        # count the launches before (one call per clone fewer than asking for each apart).
        seen = c.instances(spec.robot, spec.role, states=LIVE + GONE)
        existing = [i for i in seen if i["State"]["Name"] in LIVE]
        if existing:
            inst, origin = existing[0], Origin.REUSED
            if inst["State"]["Name"] == "stopped":
                c.api("start instance", c.ec2.start_instances, InstanceIds=[inst["InstanceId"]])
                origin = Origin.RESUMED
            return self._complete(inst, spec, net, origin)
        payload, _gzipped = INFO.fit_user_data(spec.user_data)  # cloud-init detects gzip itself
        return self._complete(self._launch(spec, net, payload, generation=len(seen)), spec, net, Origin.CREATED)

    def _launch(self, spec: CloneSpec, net: Network, user_data: bytes, generation: int) -> dict:
        c = self.client
        instance_type = self._instance_type(spec.robot)
        # ClientToken makes a retried RunInstances (lost answer, throttling) return the same
        # instance. A token stays bound to its instance after termination, so a relaunch after
        # a rollback takes the next generation (the count of its terminated predecessors).
        for _ in range(3):
            token = hashlib.sha256(f"{spec.instance_id}/{generation}".encode()).hexdigest()[:64]
            inst = c.api(
                f"launch clone {spec.hostname}", c.ec2.run_instances,
                ImageId=spec.image, InstanceType=instance_type, MinCount=1, MaxCount=1, ClientToken=token,
                KeyName=net.key_name, UserData=user_data, NetworkInterfaces=self._interfaces(spec, net),
                # IMDSv2 only: the metadata service (user-data) needs a session token.
                MetadataOptions={"HttpTokens": "required", "HttpEndpoint": "enabled"},
                # A clone's own poweroff (autostop) stops it; AWS's default, said so it stays that way.
                InstanceInitiatedShutdownBehavior="stop",
                TagSpecifications=tags.spec(["instance", "volume", "network-interface"], self.fleet, spec.role,
                                            spec.robot, name=spec.hostname),
            )["Instances"][0]
            if inst["State"]["Name"] not in GONE:
                return inst
            generation += 1
        raise CcrpError(f"clone {spec.hostname}: AWS keeps returning terminated instances for its client token")

    def _interfaces(self, spec: CloneSpec, net: Network) -> list[dict]:
        """A clone's one interface in the common subnet at its address. Behind an entry gateway, the
        gateway's first interface is in its public subnet (where its Elastic IP is routed to the
        internet gateway), its second at gateway_ip in the clones' subnet (their way in and out); a
        bake's builder has only the public one, so it is reached whether the gateway runs or not."""
        common = {"SubnetId": net.subnet_id, "Groups": [net.security_group_id], "PrivateIpAddress": spec.common_ip,
                  "DeleteOnTermination": True}
        if not self.behind or spec.role == "clone":
            return [{"DeviceIndex": 0, "AssociatePublicIpAddress": False, **common}]
        if not (net.gateway_subnet_id and net.gateway_group_id):
            raise CcrpError(f"fleet {self.fleet!r} has no entry gateway subnet yet", hint="run `ccrp fleet up` (bootstrap)")
        public = {"DeviceIndex": 0, "SubnetId": net.gateway_subnet_id, "Groups": [net.gateway_group_id],
                  "DeleteOnTermination": True}
        if spec.role == GATEWAY_ROLE:  # EC2 takes no AssociatePublicIpAddress with two interfaces
            return [public, {"DeviceIndex": 1, **common}]
        return [public | {"AssociatePublicIpAddress": False}]

    def _complete(self, inst: dict, spec: CloneSpec, net: Network, origin: Origin) -> CloneRecord:
        c = self.client
        iid = inst["InstanceId"]
        legs = sorted(inst.get("NetworkInterfaces", []), key=lambda n: n.get("Attachment", {}).get("DeviceIndex", 0))
        new_eip: dict | None = None
        eip: dict | None = None
        # Behind an entry gateway a clone has no public address: its robot comes through the gateway's.
        public = spec.role != "clone" or not self.behind
        step = "disable source/dest check"
        try:
            # The clone forwards its robot's VPN subnet, the gateway the clones' packets out: AWS
            # drops such packets unless this is off (per interface: EC2 refuses the instance's
            # attribute on an instance with two).
            if len(legs) > 1:
                for leg in legs:
                    c.api(step, c.ec2.modify_network_interface_attribute, NetworkInterfaceId=leg["NetworkInterfaceId"],
                          SourceDestCheck={"Value": False})
            else:
                c.api(step, c.ec2.modify_instance_attribute, InstanceId=iid, SourceDestCheck={"Value": False})
            if spec.vpn_subnet:
                step = f"route {spec.vpn_subnet} to the clone"
                self._route(net, spec.vpn_subnet, InstanceId=iid)
            if spec.role == GATEWAY_ROLE:  # the clones' way out: a gateway made again is a new interface
                step = "route the clones' subnet out through the gateway"
                self._route(net, "0.0.0.0/0", NetworkInterfaceId=legs[-1]["NetworkInterfaceId"])
            step = "wait until running"
            c.wait("instance_running", [iid])  # an Elastic IP attaches only to a running instance
            if public:
                step = "allocate the Elastic IP"
                eip, made = self._eip(spec.robot, spec.role)
                new_eip = eip if made else None
                if eip.get("InstanceId") != iid:
                    step = "associate the Elastic IP"
                    # EC2 wants the interface named on an instance with two (the first: the public one).
                    to = {"NetworkInterfaceId": legs[0]["NetworkInterfaceId"]} if len(legs) > 1 else {"InstanceId": iid}
                    c.api(step, c.ec2.associate_address, AllocationId=eip["AllocationId"], AllowReassociation=True, **to)
            elif origin is not Origin.CREATED:  # kept from per-clone days: its address goes back
                step = "release the clone's Elastic IP"
                for held in c.describe("elastic_ip", tags.filters(self.fleet, spec.role, spec.robot)):
                    c.release(held)
        except Exception as exc:
            undone = self._roll_back(iid if origin is Origin.CREATED else None, new_eip)
            raise CcrpError(
                f"clone {spec.hostname}: {step} failed ({getattr(exc, 'message', exc)}); "
                f"rolled back {', '.join(undone) or 'nothing'}",
                hint=getattr(exc, "hint", None),
            ) from exc
        record = self._record(inst, origin=origin, public_ip=eip["PublicIp"] if eip else None)
        return record if public else record.model_copy(update={"public_ip": None})

    def _roll_back(self, instance_id: str | None, eip: dict | None) -> list[str]:
        """Remove what the failed attempt created; keep going on errors (best effort, reported)."""
        c = self.client
        steps = []
        if eip:
            steps.append((f"Elastic IP {eip.get('PublicIp')}", lambda: c.release(eip)))
        if instance_id:
            steps.append((f"instance {instance_id}", lambda: c.terminate_ids([instance_id])))
        undone = []
        for what, undo in steps:
            try:
                undo()
                undone.append(what)
            except CcrpError as exc:
                undone.append(f"NOT {what} ({exc.message})")
        return undone

    def _route(self, net: Network, cidr: str, **target: str) -> None:
        """`cidr` in the clones' route table leads to `target` (InstanceId= or NetworkInterfaceId=)."""
        c = self.client
        # Created first, looked at only when it exists: a new clone's route is one call, and no
        # clone reads the whole table (every robot's route) while a fleet of N is made.
        try:
            c.api("create route", c.ec2.create_route, RouteTableId=net.route_table_id, DestinationCidrBlock=cidr, **target)
            return
        except CcrpError as exc:
            if error_code(exc.__cause__) != "RouteAlreadyExists":
                raise
        rt = c.api("describe route table", c.ec2.describe_route_tables, RouteTableIds=[net.route_table_id])["RouteTables"][0]
        current: dict = next((r for r in rt["Routes"] if r.get("DestinationCidrBlock") == cidr), {})
        if any(current.get(k) != v for k, v in target.items()):  # left by an earlier instance of this robot
            c.api("replace route", c.ec2.replace_route, RouteTableId=net.route_table_id,
                     DestinationCidrBlock=cidr, **target)

    def _eip(self, robot: str, role: str) -> tuple[dict, bool]:
        """The robot's Elastic IP (kept across re-runs), allocated when missing."""
        c = self.client
        found = c.api("describe Elastic IPs", c.ec2.describe_addresses, Filters=tags.filters(self.fleet, role, robot))["Addresses"]
        if found:
            return found[0], False
        eip = c.api("allocate Elastic IP", c.ec2.allocate_address, Domain="vpc",
                       TagSpecifications=tags.spec(["elastic-ip"], self.fleet, role, robot))
        return eip, True

    def query(self) -> dict[str, CloneRecord]:
        c = self.client
        return {r.robot: r for r in map(self._record, c.instances())}

    def gateway(self) -> CloneRecord | None:
        """The fleet's entry gateway: the instance of role "gateway" (its Elastic IP, tagged apart
        from it, is kept when it goes and associated again with the next one)."""
        found = self.client.instances(GATEWAY, GATEWAY_ROLE)
        return self._record(found[0]) if found else None

    def stop_instance(self, robot: str) -> bool:
        c = self.client
        running = [i["InstanceId"] for i in c.instances(robot, states=["pending", "running"])]
        if running:
            c.api("stop instance", c.ec2.stop_instances, InstanceIds=running)
        return bool(running)

    def terminate(self, robot: str) -> bool:
        """The robot's owned instances and its Elastic IP (clone or `snapshot bake` builder);
        nothing without the fleet's tags."""
        c = self.client
        instances = [i["InstanceId"] for i in c.instances(robot, role=None)]
        for eip in c.describe("elastic_ip", tags.filters(self.fleet, None, robot)):
            c.release(eip)
        if instances:
            c.terminate_ids(instances)
        return bool(instances)

    def console_output(self, robot: str) -> str:
        c = self.client
        instances = c.instances(robot, role=None)
        if not instances:
            raise CcrpError(f"robot {robot!r} has no clone on AWS", hint=f"ccrp clone create --robot {robot}")
        iid = instances[0]["InstanceId"]
        try:  # the live buffer (Nitro instances) shows cloud-init's host keys minutes sooner
            out = c.api("get console output", c.ec2.get_console_output, InstanceId=iid, Latest=True)
        except CcrpError as exc:
            if error_code(exc.__cause__) != "UnsupportedOperation":
                raise
            out = c.api("get console output", c.ec2.get_console_output, InstanceId=iid)
        out = out.get("Output") or ""
        try:  # the API returns it base64-encoded
            return base64.b64decode(out, validate=True).decode(errors="replace")
        except ValueError:
            return out

    # -- doctor ------------------------------------------------------------------------------
    def check_credentials(self) -> str:
        c = self.client
        sts = c.session.client("sts")
        ident = c.api("get caller identity", sts.get_caller_identity)
        return f"account {ident['Account']} as {ident['Arn']}"

    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]:
        """The account's quotas in the region that a clone draws on, with what the clones of
        `robots` take: an Elastic IP (none for a robot that holds one already), counted against
        `vpc-max-elastic-ips` (DescribeAccountAttributes) and the region's addresses; its instance
        type's vCPUs against Running On-Demand Standard instances (Service Quotas L-1216C47A) and
        the running standard instances, or, where Service Quotas does not answer, one instance
        against `max-instances`."""
        c = self.client
        where = f"region {self.settings.region}"
        attrs = c.api("describe account attributes", c.ec2.describe_account_attributes)["AccountAttributes"]
        values = {a["AttributeName"]: a["AttributeValues"][0]["AttributeValue"] for a in attrs if a.get("AttributeValues")}
        found: list[Quota] = []
        # Behind an entry gateway a clone takes no Elastic IP; the fleet takes one for its gateway
        # while it holds none (it is kept while the gateway is made again), and an instance of the
        # gateway's type while there is none.
        instance = 1.0 if self.behind and robots and self.gateway() is None else 0.0
        if values.get("vpc-max-elastic-ips", "").isdigit():
            eips = c.api("describe Elastic IPs", c.ec2.describe_addresses)["Addresses"]
            held = {tags.as_dict(a).get(LABEL_ROBOT) for a in eips if tags.owned_by(a, self.fleet)}
            address = 1.0 if self.behind and robots and GATEWAY not in held else 0.0
            found.append(Quota(name="EC2-VPC Elastic IPs", scope=where, limit=float(values["vpc-max-elastic-ips"]),
                               used=len(eips), per_clone=0 if self.behind else 1,
                               per_robot={r: 0.0 for r in robots if r in held}, once=address,
                               hint="raise EC2-VPC Elastic IPs (L-0263D0A3) in the Service Quotas console"))
        running = self._running_on_demand()
        types = {r: self._instance_type(r) for r in robots}
        gateway_type = self._instance_type(GATEWAY)
        # Running On-Demand Standard instances, in vCPUs; unreadable: account attributes below.
        vcpus = self._service_quota("ec2", "L-1216C47A")
        if vcpus is not None:
            sizes = self._type_vcpus({i["InstanceType"] for i in running} | set(types.values())
                                     | {self.settings.instance_type, gateway_type})

            def standard(instance_type: str) -> float:
                return float(sizes[instance_type]) if is_standard(instance_type) else 0.0

            per = standard(self.settings.instance_type)
            found.append(Quota(
                name="Running On-Demand Standard instances (vCPUs)", scope=where, limit=vcpus,
                used=sum(standard(i["InstanceType"]) for i in running), per_clone=per,
                per_robot={r: n for r, t in types.items() if (n := standard(t)) != per},
                once=instance * standard(gateway_type), hint="raise Running On-Demand Standard instances (L-1216C47A) in the Service Quotas console"))
        elif values.get("max-instances", "").isdigit():
            found.append(Quota(name="max-instances (running instances)", scope=where,
                               limit=float(values["max-instances"]), used=len(running), per_clone=1, once=instance))
        routes = self._service_quota("vpc", "L-93826ACB")
        if routes is not None:
            # Each clone has a route in the clones' route table (its robot's VPN subnet): AWS's
            # default of 50 per table holds the default route and 49 clones, whatever the entry.
            net = network.find(c) if c.net is None else c.net
            table = (c.api("describe route table", c.ec2.describe_route_tables, RouteTableIds=[net.route_table_id])
                     ["RouteTables"][0]["Routes"] if net else [{"DestinationCidrBlock": "0.0.0.0/0"}])  # bootstrap makes it
            found.append(Quota(name="Routes per route table", scope=f"the clones' route table of fleet {self.fleet!r}",
                               limit=routes, used=sum(1 for r in table if r.get("GatewayId") != "local"), per_clone=1,
                               hint="raise Routes per route table (L-93826ACB; up to 1000) in the Service Quotas console"))
        return found

    def _instance_type(self, robot: str) -> str:
        if robot == GATEWAY:
            return self.settings.gateway_instance_type
        override = self.inv.robot(robot)
        return (override.instance_type if override and override.instance_type else self.settings.instance_type)

    def _running_on_demand(self) -> list[dict]:
        """Every pending or running On-Demand instance of the account in the region (what the
        running-instance quotas count), the fleet's and anyone else's."""
        c = self.client
        pages = c.api("describe instances", lambda: list(c.ec2.get_paginator("describe_instances").paginate(
            Filters=[{"Name": "instance-state-name", "Values": ["pending", "running"]}])))
        return [i for page in pages for r in page.get("Reservations", []) for i in r["Instances"]
                if i.get("InstanceLifecycle") not in ("spot", "scheduled")]

    def _type_vcpus(self, instance_types: set[str]) -> dict[str, int]:
        """instance type -> its default vCPUs (DescribeInstanceTypes, 100 types a call)."""
        c = self.client
        names, sizes = sorted(instance_types), {}
        for k in range(0, len(names), 100):
            for t in c.api("describe instance types", c.ec2.describe_instance_types,
                              InstanceTypes=names[k:k + 100])["InstanceTypes"]:
                sizes[t["InstanceType"]] = t["VCpuInfo"]["DefaultVCpus"]
        return sizes

    def _service_quota(self, service: str, code: str) -> float | None:
        """A quota's value from Service Quotas (the account's, raised or AWS's default), if readable."""
        c = self.client
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            if self._service_quotas is None:
                self._service_quotas = c.session.client("service-quotas", config=c.config)
            return float(c.api("get service quota", self._service_quotas.get_service_quota, ServiceCode=service,
                               QuotaCode=code)["Quota"]["Value"])
        except (CcrpError, BotoCoreError, ClientError):
            return None  # no permission, or not offered here: the cloud's refusal stays the last word
