"""AWS provider: a clone is an EC2 instance in the fleet's common subnet with a fixed private IP
(its common-network address), an Elastic IP (public network), source/dest check off and a route
for its robot's VPN subnet, so clones reach each other's robots through each other.

Every call goes through CloudProvider.api (retry.py); botocore's own retries are switched off so
that backoff lives in one place.

Zones: an AWS subnet lives in one zone and each clone's private IP is fixed inside the common
subnet, so zone fallback (inventory provider.zones, in order) happens where the subnet is placed,
at bootstrap. A capacity error at launch is reported with its hint rather than moved elsewhere.
"""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

from ...errors import CcrpError
from ...models.inventory import Inventory
from ..base import LABEL_ROBOT, CloneRecord, CloneSpec, CloneState, Origin, Quota
from ..cloud import CloudProvider
from . import INFO, network, tags
from .errors import INSTALL_HINT, as_ccrp, classify, error_code
from .images import Images
from .network import Network
from .owned import KINDS, LIVE, Owned
from .settings import AwsSettings

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


class AwsProvider(Images, Owned, CloudProvider):
    kind = "aws"
    abilities = INFO.abilities

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        super().__init__(inv, workdir)
        try:
            import boto3
            from botocore.config import Config
            from botocore.exceptions import BotoCoreError
        except ImportError:
            raise CcrpError("the AWS SDK (boto3) is not installed", hint=INSTALL_HINT) from None
        self.settings = cast(AwsSettings, inv.provider)  # get_provider picked this backend by these settings' kind
        try:
            self.session = boto3.Session(profile_name=self.settings.profile, region_name=self.settings.region)
        except BotoCoreError as exc:  # unknown profile
            raise as_ccrp("session", exc) from exc
        # retry.call is the one place for retries: botocore's own are off.
        self._config = config = Config(retries={"total_max_attempts": 1}, connect_timeout=10, read_timeout=60)
        self.ec2 = self.session.client("ec2", config=config)
        self._net: Network | None = None
        self._service_quotas: Any = None  # its client (boto3's, untyped), made when quotas are first read

    # -- errors ------------------------------------------------------------------------------
    def classify_error(self, exc: BaseException):
        return classify(exc)

    def api(self, what: str, fn, *args, **kwargs):
        """CloudProvider.api, with SDK errors turned into one-line CcrpErrors (cause kept)."""
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            return super().api(what, fn, *args, **kwargs)
        except (BotoCoreError, ClientError) as exc:
            raise as_ccrp(what, exc) from exc

    def _wait(self, waiter: str, ids: list[str]) -> None:
        w = self.ec2.get_waiter(waiter)
        self.api(waiter.replace("_", " "), w.wait, InstanceIds=ids, WaiterConfig={"Delay": 3, "MaxAttempts": 100})

    # -- lookups -----------------------------------------------------------------------------
    def _describe(self, kind: str, filters: list[dict]) -> list[dict]:
        op, key, _, _, extra = KINDS[kind]
        extra = dict(extra)
        given = {f["Name"] for f in filters}
        filters = filters + [f for f in extra.pop("Filters", []) if f["Name"] not in given]
        if self.ec2.can_paginate(op):
            pages = self.api(op.replace("_", " "), lambda: list(self.ec2.get_paginator(op).paginate(Filters=filters, **extra)))
        else:
            pages = [self.api(op.replace("_", " "), getattr(self.ec2, op), Filters=filters, **extra)]
        items = [item for page in pages for item in page.get(key, [])]
        if kind == "instance":
            items = [i for reservation in items for i in reservation["Instances"]]
        return items

    def _instances(self, robot: str | None = None, role: str | None = "clone", states: list[str] = LIVE) -> list[dict]:
        return self._describe("instance", tags.filters(self.fleet, role, robot) + [{"Name": "instance-state-name", "Values": states}])

    @property
    def network(self) -> Network:
        if self._net is None:
            self._net = network.find(self)
        if self._net is None:
            raise CcrpError(f"fleet {self.fleet!r} has no network on AWS yet", hint="`ccrp fleet up` creates it (bootstrap)")
        return self._net

    def _record(self, inst: dict, origin: Origin | None = None, public_ip: str | None = None) -> CloneRecord:
        return CloneRecord(
            robot=tags.as_dict(inst).get(LABEL_ROBOT, ""), provider_id=inst["InstanceId"],
            state=CloneState.of(inst["State"]["Name"], STATES), status=inst["State"]["Name"], public_ip=public_ip or inst.get("PublicIpAddress"),
            common_ip=inst.get("PrivateIpAddress"), origin=origin,
        )

    # -- lifecycle ---------------------------------------------------------------------------
    def bootstrap(self) -> None:
        self._net = network.ensure(self)

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Reuse the robot's owned instance, or launch one; then converge its route and Elastic IP.
        On failure, remove only what this call created."""
        net = self.network
        # One look at the robot's instances in every state: a live one is reused; the gone ones
        # count the launches before (one call per clone fewer than asking for each apart).
        seen = self._instances(spec.robot, spec.role, states=LIVE + GONE)
        existing = [i for i in seen if i["State"]["Name"] in LIVE]
        if existing:
            inst, origin = existing[0], Origin.REUSED
            if inst["State"]["Name"] == "stopped":
                self.api("start instance", self.ec2.start_instances, InstanceIds=[inst["InstanceId"]])
                origin = Origin.RESUMED
            return self._complete(inst, spec, net, origin)
        payload, _gzipped = INFO.fit_user_data(spec.user_data)  # cloud-init detects gzip itself
        return self._complete(self._launch(spec, net, payload, generation=len(seen)), spec, net, Origin.CREATED)

    def _launch(self, spec: CloneSpec, net: Network, user_data: bytes, generation: int) -> dict:
        instance_type = self._instance_type(spec.robot)
        # ClientToken makes a retried RunInstances (lost answer, throttling) return the same
        # instance. A token stays bound to its instance after termination, so a relaunch after
        # a rollback takes the next generation (the count of its terminated predecessors).
        for _ in range(3):
            token = hashlib.sha256(f"{spec.instance_id}/{generation}".encode()).hexdigest()[:64]
            inst = self.api(
                f"launch clone {spec.hostname}", self.ec2.run_instances,
                ImageId=spec.image, InstanceType=instance_type, MinCount=1, MaxCount=1, ClientToken=token,
                KeyName=net.key_name, UserData=user_data,
                NetworkInterfaces=[{"DeviceIndex": 0, "SubnetId": net.subnet_id, "Groups": [net.security_group_id],
                                    "PrivateIpAddress": spec.common_ip, "AssociatePublicIpAddress": False,
                                    "DeleteOnTermination": True}],
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

    def _complete(self, inst: dict, spec: CloneSpec, net: Network, origin: Origin) -> CloneRecord:
        iid = inst["InstanceId"]
        new_eip: dict | None = None
        step = "disable source/dest check"
        try:
            # The clone forwards its robot's VPN subnet: AWS drops such packets unless this is off.
            self.api(step, self.ec2.modify_instance_attribute, InstanceId=iid, SourceDestCheck={"Value": False})
            if spec.vpn_subnet:
                step = f"route {spec.vpn_subnet} to the clone"
                self._route(net, spec.vpn_subnet, iid)
            step = "wait until running"
            self._wait("instance_running", [iid])  # an Elastic IP attaches only to a running instance
            step = "allocate the Elastic IP"
            eip, made = self._eip(spec.robot, spec.role)
            new_eip = eip if made else None
            if eip.get("InstanceId") != iid:
                step = "associate the Elastic IP"
                self.api(step, self.ec2.associate_address, AllocationId=eip["AllocationId"], InstanceId=iid,
                         AllowReassociation=True)
        except Exception as exc:
            undone = self._roll_back(iid if origin is Origin.CREATED else None, new_eip)
            raise CcrpError(
                f"clone {spec.hostname}: {step} failed ({getattr(exc, 'message', exc)}); "
                f"rolled back {', '.join(undone) or 'nothing'}",
                hint=getattr(exc, "hint", None),
            ) from exc
        return self._record(inst, origin=origin, public_ip=eip["PublicIp"])

    def _roll_back(self, instance_id: str | None, eip: dict | None) -> list[str]:
        """Remove what the failed attempt created; keep going on errors (best effort, reported)."""
        steps = []
        if eip:
            steps.append((f"Elastic IP {eip.get('PublicIp')}", lambda: self._release(eip)))
        if instance_id:
            steps.append((f"instance {instance_id}", lambda: self._terminate_ids([instance_id])))
        undone = []
        for what, undo in steps:
            try:
                undo()
                undone.append(what)
            except CcrpError as exc:
                undone.append(f"NOT {what} ({exc.message})")
        return undone

    def _route(self, net: Network, cidr: str, instance_id: str) -> None:
        rt = self.api("describe route table", self.ec2.describe_route_tables, RouteTableIds=[net.route_table_id])["RouteTables"][0]
        current = next((r for r in rt["Routes"] if r.get("DestinationCidrBlock") == cidr), None)
        if current is None:
            self.api("create route", self.ec2.create_route, RouteTableId=net.route_table_id,
                     DestinationCidrBlock=cidr, InstanceId=instance_id)
        elif current.get("InstanceId") != instance_id:  # left by an earlier clone of this robot
            self.api("replace route", self.ec2.replace_route, RouteTableId=net.route_table_id,
                     DestinationCidrBlock=cidr, InstanceId=instance_id)

    def _unroute(self, instance_ids: list[str]) -> None:
        """Delete the routes in the fleet's route tables that lead to these instances."""
        for rt in self._describe("route_table", tags.filters(self.fleet)):
            for r in rt["Routes"]:
                if r.get("InstanceId") in instance_ids and r.get("DestinationCidrBlock"):
                    self.api("delete route", self.ec2.delete_route, RouteTableId=rt["RouteTableId"],
                             DestinationCidrBlock=r["DestinationCidrBlock"])

    def _eip(self, robot: str, role: str) -> tuple[dict, bool]:
        """The robot's Elastic IP (kept across re-runs), allocated when missing."""
        found = self.api("describe Elastic IPs", self.ec2.describe_addresses, Filters=tags.filters(self.fleet, role, robot))["Addresses"]
        if found:
            return found[0], False
        eip = self.api("allocate Elastic IP", self.ec2.allocate_address, Domain="vpc",
                       TagSpecifications=tags.spec(["elastic-ip"], self.fleet, role, robot))
        return eip, True

    def _release(self, eip: dict) -> None:
        current = self.api("describe Elastic IP", self.ec2.describe_addresses, AllocationIds=[eip["AllocationId"]])["Addresses"]
        if current and current[0].get("AssociationId"):
            self.api("disassociate Elastic IP", self.ec2.disassociate_address, AssociationId=current[0]["AssociationId"])
        self.api("release Elastic IP", self.ec2.release_address, AllocationId=eip["AllocationId"])

    def _terminate_ids(self, ids: list[str]) -> None:
        self._unroute(ids)
        self.api("terminate instances", self.ec2.terminate_instances, InstanceIds=ids)

    def query(self) -> dict[str, CloneRecord]:
        return {r.robot: r for r in map(self._record, self._instances())}

    def stop_instance(self, robot: str) -> bool:
        running = [i["InstanceId"] for i in self._instances(robot, states=["pending", "running"])]
        if running:
            self.api("stop instance", self.ec2.stop_instances, InstanceIds=running)
        return bool(running)

    def terminate(self, robot: str) -> bool:
        """The robot's owned instances and its Elastic IP (clone or `snapshot bake` builder);
        nothing without the fleet's tags."""
        instances = [i["InstanceId"] for i in self._instances(robot, role=None)]
        for eip in self._describe("elastic_ip", tags.filters(self.fleet, None, robot)):
            self._release(eip)
        if instances:
            self._terminate_ids(instances)
        return bool(instances)

    def console_output(self, robot: str) -> str:
        instances = self._instances(robot, role=None)
        if not instances:
            raise CcrpError(f"robot {robot!r} has no clone on AWS", hint=f"ccrp clone create --robot {robot}")
        iid = instances[0]["InstanceId"]
        try:  # the live buffer (Nitro instances) shows cloud-init's host keys minutes sooner
            out = self.api("get console output", self.ec2.get_console_output, InstanceId=iid, Latest=True)
        except CcrpError as exc:
            if error_code(exc.__cause__) != "UnsupportedOperation":
                raise
            out = self.api("get console output", self.ec2.get_console_output, InstanceId=iid)
        out = out.get("Output") or ""
        try:  # the API returns it base64-encoded
            return base64.b64decode(out, validate=True).decode(errors="replace")
        except ValueError:
            return out

    # -- doctor ------------------------------------------------------------------------------
    def check_credentials(self) -> str:
        sts = self.session.client("sts")
        ident = self.api("get caller identity", sts.get_caller_identity)
        return f"account {ident['Account']} as {ident['Arn']}"

    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]:
        """The account's quotas in the region that a clone draws on, with what the clones of
        `robots` take: an Elastic IP (none for a robot that holds one already), counted against
        `vpc-max-elastic-ips` (DescribeAccountAttributes) and the region's addresses; its instance
        type's vCPUs against Running On-Demand Standard instances (Service Quotas L-1216C47A) and
        the running standard instances, or, where Service Quotas does not answer, one instance
        against `max-instances`."""
        where = f"region {self.settings.region}"
        attrs = self.api("describe account attributes", self.ec2.describe_account_attributes)["AccountAttributes"]
        values = {a["AttributeName"]: a["AttributeValues"][0]["AttributeValue"] for a in attrs if a.get("AttributeValues")}
        found: list[Quota] = []
        if values.get("vpc-max-elastic-ips", "").isdigit():
            eips = self.api("describe Elastic IPs", self.ec2.describe_addresses)["Addresses"]
            held = {tags.as_dict(a).get(LABEL_ROBOT) for a in eips if tags.owned_by(a, self.fleet)}
            found.append(Quota(name="EC2-VPC Elastic IPs", scope=where, limit=float(values["vpc-max-elastic-ips"]),
                               used=len(eips), per_clone=1, per_robot={r: 0.0 for r in robots if r in held},
                               hint="raise EC2-VPC Elastic IPs (L-0263D0A3) in the Service Quotas console"))
        running = self._running_on_demand()
        types = {r: self._instance_type(r) for r in robots}
        vcpus = self._vcpu_quota()
        if vcpus is not None:
            sizes = self._type_vcpus({i["InstanceType"] for i in running} | set(types.values())
                                     | {self.settings.instance_type})

            def standard(instance_type: str) -> float:
                return float(sizes[instance_type]) if is_standard(instance_type) else 0.0

            per = standard(self.settings.instance_type)
            found.append(Quota(
                name="Running On-Demand Standard instances (vCPUs)", scope=where, limit=vcpus,
                used=sum(standard(i["InstanceType"]) for i in running), per_clone=per,
                per_robot={r: n for r, t in types.items() if (n := standard(t)) != per},
                hint="raise Running On-Demand Standard instances (L-1216C47A) in the Service Quotas console"))
        elif values.get("max-instances", "").isdigit():
            found.append(Quota(name="max-instances (running instances)", scope=where,
                               limit=float(values["max-instances"]), used=len(running), per_clone=1))
        return found

    def _instance_type(self, robot: str) -> str:
        override = self.inv.robot(robot)
        return (override.instance_type if override and override.instance_type else self.settings.instance_type)

    def _running_on_demand(self) -> list[dict]:
        """Every pending or running On-Demand instance of the account in the region (what the
        running-instance quotas count), the fleet's and anyone else's."""
        pages = self.api("describe instances", lambda: list(self.ec2.get_paginator("describe_instances").paginate(
            Filters=[{"Name": "instance-state-name", "Values": ["pending", "running"]}])))
        return [i for page in pages for r in page.get("Reservations", []) for i in r["Instances"]
                if i.get("InstanceLifecycle") not in ("spot", "scheduled")]

    def _type_vcpus(self, instance_types: set[str]) -> dict[str, int]:
        """instance type -> its default vCPUs (DescribeInstanceTypes, 100 types a call)."""
        names, sizes = sorted(instance_types), {}
        for k in range(0, len(names), 100):
            for t in self.api("describe instance types", self.ec2.describe_instance_types,
                              InstanceTypes=names[k:k + 100])["InstanceTypes"]:
                sizes[t["InstanceType"]] = t["VCpuInfo"]["DefaultVCpus"]
        return sizes

    def _vcpu_quota(self) -> float | None:
        """Service Quotas L-1216C47A (Running On-Demand Standard instances, in vCPUs), if readable."""
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            if self._service_quotas is None:
                self._service_quotas = self.session.client("service-quotas", config=self._config)
            return float(self.api("get service quota", self._service_quotas.get_service_quota, ServiceCode="ec2",
                                  QuotaCode="L-1216C47A")["Quota"]["Value"])
        except (CcrpError, BotoCoreError, ClientError):
            return None  # no permission, or not offered here: fall back to account attributes
