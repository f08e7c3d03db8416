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
from pathlib import Path

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...render.limits import fit_user_data
from ..base import LABEL_ROBOT, LABEL_ROLE, CloneRecord, CloneSpec, CloneState, OwnedResource, Quota, SnapshotRecord
from . import INFO
from ..cloud import CloudProvider
from . import network, tags
from .errors import INSTALL_HINT, as_ccrp, classify, error_code

LIVE = ["pending", "running", "stopping", "stopped"]
GONE = ["shutting-down", "terminated"]
# EC2's instance states in ccrp's words.
STATES = {"pending": CloneState.PENDING, "running": CloneState.RUNNING, "stopping": CloneState.STOPPING,
          "stopped": CloneState.STOPPED, "shutting-down": CloneState.DELETING, "terminated": CloneState.DELETING}

# kind -> (describe call, result key, id filter, id field, extra describe args)
KINDS: dict[str, tuple[str, str, str, str, dict]] = {
    "instance": ("describe_instances", "Reservations", "instance-id", "InstanceId",
                 {"Filters": [{"Name": "instance-state-name", "Values": LIVE}]}),
    "elastic_ip": ("describe_addresses", "Addresses", "allocation-id", "AllocationId", {}),
    "volume": ("describe_volumes", "Volumes", "volume-id", "VolumeId", {}),
    "image": ("describe_images", "Images", "image-id", "ImageId", {"Owners": ["self"]}),
    "snapshot": ("describe_snapshots", "Snapshots", "snapshot-id", "SnapshotId", {"OwnerIds": ["self"]}),
    "security_group": ("describe_security_groups", "SecurityGroups", "group-id", "GroupId", {}),
    "key_pair": ("describe_key_pairs", "KeyPairs", "key-pair-id", "KeyPairId", {}),
    "route_table": ("describe_route_tables", "RouteTables", "route-table-id", "RouteTableId", {}),
    "subnet": ("describe_subnets", "Subnets", "subnet-id", "SubnetId", {}),
    "internet_gateway": ("describe_internet_gateways", "InternetGateways", "internet-gateway-id", "InternetGatewayId", {}),
    "vpc": ("describe_vpcs", "Vpcs", "vpc-id", "VpcId", {}),
}
# Teardown order: what depends on something is removed before it. Snapshots outlive the fleet
# (as on Docker): `ccrp snapshot delete` removes them.
TEARDOWN = ["instance", "elastic_ip", "volume", "security_group", "key_pair", "route_table", "subnet",
            "internet_gateway", "vpc"]


class AwsProvider(CloudProvider):
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
        self.settings = inv.provider
        try:
            self.session = boto3.Session(profile_name=self.settings.profile, region_name=self.settings.region)
        except BotoCoreError as exc:  # unknown profile
            raise as_ccrp("session", exc) from exc
        # retry.call is the one place for retries: botocore's own are off.
        self._config = config = Config(retries={"total_max_attempts": 1}, connect_timeout=10, read_timeout=60)
        self.ec2 = self.session.client("ec2", config=config)
        self._net: network.Network | None = None

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
    def network(self) -> network.Network:
        if self._net is None:
            self._net = network.find(self)
        if self._net is None:
            raise CcrpError(f"fleet {self.fleet!r} has no network on AWS yet", hint="`ccrp fleet up` creates it (bootstrap)")
        return self._net

    def _record(self, inst: dict, created: bool = False, public_ip: str | None = None) -> CloneRecord:
        return CloneRecord(
            robot=tags.as_dict(inst).get(LABEL_ROBOT, ""), provider_id=inst["InstanceId"],
            state=CloneState.of(inst["State"]["Name"], STATES), status=inst["State"]["Name"], public_ip=public_ip or inst.get("PublicIpAddress"),
            common_ip=inst.get("PrivateIpAddress"), created=created,
        )

    # -- lifecycle ---------------------------------------------------------------------------
    def bootstrap(self) -> None:
        self._net = network.ensure(self)

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Reuse the robot's owned instance, or launch one; then converge its route and Elastic IP.
        On failure, remove only what this call created."""
        net = self.network
        existing = self._instances(spec.robot, spec.role)
        if existing:
            inst = existing[0]
            if inst["State"]["Name"] == "stopped":
                self.api("start instance", self.ec2.start_instances, InstanceIds=[inst["InstanceId"]])
            return self._complete(inst, spec, net, created=False)
        payload, _gzipped = fit_user_data("aws", spec.user_data)  # cloud-init detects gzip itself
        return self._complete(self._launch(spec, net, payload), spec, net, created=True)

    def _launch(self, spec: CloneSpec, net: network.Network, user_data: bytes) -> dict:
        robot = self.inv.robot(spec.robot)
        instance_type = (robot.instance_type if robot and robot.instance_type else self.settings.instance_type)
        # ClientToken makes a retried RunInstances (lost answer, throttling) return the same
        # instance. A token stays bound to its instance after termination, so a relaunch after
        # a rollback takes the next generation.
        generation = len(self._instances(spec.robot, spec.role, states=GONE))
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
                TagSpecifications=tags.spec(["instance", "volume", "network-interface"], self.fleet, spec.role,
                                            spec.robot, name=spec.hostname),
            )["Instances"][0]
            if inst["State"]["Name"] not in GONE:
                return inst
            generation += 1
        raise CcrpError(f"clone {spec.hostname}: AWS keeps returning terminated instances for its client token")

    def _complete(self, inst: dict, spec: CloneSpec, net: network.Network, created: bool) -> CloneRecord:
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
            undone = self._roll_back(iid if created else None, new_eip)
            raise CcrpError(
                f"clone {spec.hostname}: {step} failed ({getattr(exc, 'message', exc)}); "
                f"rolled back {', '.join(undone) or 'nothing'}",
                hint=getattr(exc, "hint", None),
            ) from exc
        return self._record(inst, created=created, public_ip=eip["PublicIp"])

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

    def _route(self, net: network.Network, cidr: str, instance_id: str) -> None:
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

    # -- snapshots ---------------------------------------------------------------------------
    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        instances = self._instances(robot, role=None)
        if not instances:
            raise CcrpError(f"robot {robot!r} has no clone to capture", hint=f"ccrp clone create --robot {robot}")
        # A builder's AMI is a build, not a robot's clone: no robot tag, source "build".
        source = robot if tags.as_dict(instances[0]).get(LABEL_ROLE) == "clone" else None
        # AMI names allow letters, digits and ()[] ./-'@_ only.
        ami_name = "".join(c if c.isalnum() or c in "()[] ./-'@_" else "-" for c in name)[:128]
        image_id = self.api(
            "create image", self.ec2.create_image, InstanceId=instances[0]["InstanceId"], Name=ami_name,
            Description=f"ccrp fleet {self.fleet}: " + (f"clone of {robot}" if source else "baked by snapshot bake"),
            TagSpecifications=tags.spec(["image"], self.fleet, "snapshot", source, name=ami_name),
        )["ImageId"]
        # `snapshot bake` deletes the builder right after this returns: wait until the AMI is usable.
        self.api("wait for image", self.ec2.get_waiter("image_available").wait, ImageIds=[image_id],
                 WaiterConfig={"Delay": 10, "MaxAttempts": 180})
        image = self._describe("image", [{"Name": "image-id", "Values": [image_id]}])[0]
        # The EBS snapshots get the tags too (gc finds them if their image is ever lost). Tagged
        # afterwards rather than in CreateImage's TagSpecifications, which moto does not model.
        snaps = _backing(image)
        if snaps:
            self.api("tag snapshots", self.ec2.create_tags, Resources=sorted(snaps),
                     Tags=tags.tags(self.fleet, "snapshot", source, name=ami_name))
        return self._snapshot_record(image)

    def _snapshot_record(self, image: dict) -> SnapshotRecord:
        gib = sum(m.get("Ebs", {}).get("VolumeSize", 0) for m in image.get("BlockDeviceMappings", []))
        return SnapshotRecord(id=image["ImageId"], name=image.get("Name", ""), created=image.get("CreationDate", "")[:19],
                              source=tags.as_dict(image).get(LABEL_ROBOT) or "build", size_mb=gib * 1024.0 or None)

    def list_snapshots(self) -> list[SnapshotRecord]:
        images = self._describe("image", tags.filters(self.fleet, "snapshot"))
        return sorted(map(self._snapshot_record, images), key=lambda s: s.created)

    def resolve_image(self, image: str) -> str:
        """The AMI id an image names: an AMI id as is; an SSM parameter (Debian publishes its current
        AMI as /aws/service/debian/release/bookworm/latest/amd64; EC2's `resolve:ssm:` form too) as
        the id it holds now, so that the fleet's state records which AMI was booted."""
        name = image.removeprefix("resolve:ssm:")
        if not name.startswith("/"):
            return image
        ssm = self.session.client("ssm", config=self._config)
        return self.api(f"get SSM parameter {name}", ssm.get_parameter, Name=name)["Parameter"]["Value"]

    def has_image(self, image: str) -> bool:
        key = "image-id" if image.startswith("ami-") else "name"
        return bool(self.api("describe images", self.ec2.describe_images, Filters=[{"Name": key, "Values": [image]}])["Images"])

    def delete_snapshot(self, snapshot_id: str) -> None:
        key = "image-id" if snapshot_id.startswith("ami-") else "name"
        found = self._describe("image", tags.filters(self.fleet, "snapshot") + [{"Name": key, "Values": [snapshot_id]}])
        if not found:
            raise CcrpError(f"snapshot {snapshot_id} is not an image of fleet {self.fleet!r}", hint="ccrp snapshot list")
        self._delete("image", found[0]["ImageId"])

    # -- everything owned (teardown, gc) -----------------------------------------------------
    def list_owned(self) -> list[OwnedResource]:
        owned: list[OwnedResource] = []
        backing: set[str] = set()  # EBS snapshots of an owned image go with their image
        for kind in KINDS:
            for item in self._describe(kind, tags.filters(self.fleet)):
                if kind == "image":
                    backing |= _backing(item)
                rid = item[KINDS[kind][3]]
                if kind == "snapshot" and rid in backing:
                    continue
                t = tags.as_dict(item)
                name = t.get("Name") or item.get("GroupName") or item.get("KeyName") or item.get("PublicIp") or ""
                owned.append(OwnedResource(kind=kind, id=rid, name=name, robot=t.get(LABEL_ROBOT)))
        return owned

    def delete_owned(self, resource: OwnedResource) -> None:
        if not self._delete(resource.kind, resource.id):
            raise CcrpError(f"{resource.kind} {resource.id} is not owned by fleet {self.fleet!r} (or is gone)")

    def _delete(self, kind: str, rid: str) -> bool:
        """Delete one resource after checking, again, that it carries the fleet's tags.
        False when there is no such owned resource (never touched)."""
        if kind not in KINDS:
            raise CcrpError(f"unknown AWS resource kind {kind!r}")
        found = self._describe(kind, tags.filters(self.fleet) + [{"Name": KINDS[kind][2], "Values": [rid]}])
        if not found:
            return False
        item, ec2 = found[0], self.ec2
        if kind == "instance":
            self._terminate_ids([rid])
        elif kind == "elastic_ip":
            self._release(item)
        elif kind == "volume" and item["State"] != "available":
            if item["State"] != "in-use":
                return False  # deleting with its terminated instance
            raise CcrpError(f"volume {rid} is attached to an instance", hint="delete the instance first")
        elif kind == "image":
            self.api("deregister image", ec2.deregister_image, ImageId=rid)
            # Its EBS snapshots were made by CreateImage from the fleet's clone: they go with it.
            for snap in sorted(_backing(item)):
                self.api("delete snapshot", ec2.delete_snapshot, SnapshotId=snap)
        elif kind == "route_table":
            for a in item.get("Associations", []):
                if not a.get("Main"):
                    self.api("disassociate route table", ec2.disassociate_route_table, AssociationId=a["RouteTableAssociationId"])
            self.api("delete route table", ec2.delete_route_table, RouteTableId=rid)
        elif kind == "internet_gateway":
            for a in item.get("Attachments", []):
                self.api("detach internet gateway", ec2.detach_internet_gateway, InternetGatewayId=rid, VpcId=a["VpcId"])
            self.api("delete internet gateway", ec2.delete_internet_gateway, InternetGatewayId=rid)
        else:
            op, arg = {"volume": ("delete_volume", "VolumeId"), "snapshot": ("delete_snapshot", "SnapshotId"),
                       "security_group": ("delete_security_group", "GroupId"), "key_pair": ("delete_key_pair", "KeyName"),
                       "subnet": ("delete_subnet", "SubnetId"), "vpc": ("delete_vpc", "VpcId")}[kind]
            self.api(op.replace("_", " "), getattr(ec2, op), **{arg: item["KeyName"] if kind == "key_pair" else rid})
        return True

    def teardown(self) -> list[str]:
        """Everything the fleet owns except its snapshots, dependents first."""
        owned = sorted((r for r in self.list_owned() if r.kind in TEARDOWN), key=lambda r: TEARDOWN.index(r.kind))
        removed: list[str] = []
        instances = [r.id for r in owned if r.kind == "instance"]
        if instances:
            self._terminate_ids(instances)
            # Security groups, subnets and volumes stay in use until the instances are really gone.
            self._wait("instance_terminated", instances)
            removed += [f"instance {r.name or r.id}" for r in owned if r.kind == "instance"]
        for r in owned:
            if r.kind != "instance" and self._delete(r.kind, r.id):
                removed.append(f"{r.kind} {r.name or r.id}")
        self._net = None
        return removed

    def leftovers(self) -> list[str]:
        return [f"{r.kind} {r.name or r.id}" for r in self.list_owned() if r.kind in TEARDOWN]

    # -- doctor ------------------------------------------------------------------------------
    def check_credentials(self) -> str:
        sts = self.session.client("sts")
        ident = self.api("get caller identity", sts.get_caller_identity)
        return f"account {ident['Account']} as {ident['Arn']}"

    def quotas(self) -> list[Quota]:
        """(quota, limit, what the fleet needs) where the API tells the limit."""
        robots = max(len(self.inv.robots), 1)
        attrs = self.api("describe account attributes", self.ec2.describe_account_attributes)["AccountAttributes"]
        values = {a["AttributeName"]: a["AttributeValues"][0]["AttributeValue"] for a in attrs if a.get("AttributeValues")}
        found: list[Quota] = []
        if values.get("vpc-max-elastic-ips", "").isdigit():
            found.append(Quota(name="Elastic IPs (one per clone)", limit=float(values["vpc-max-elastic-ips"]), need=robots))
        vcpus = self._vcpu_quota()
        if vcpus is not None:
            per_clone = self.api("describe instance types", self.ec2.describe_instance_types,
                                 InstanceTypes=[self.settings.instance_type])["InstanceTypes"][0]["VCpuInfo"]["DefaultVCpus"]
            found.append(Quota(name="running on-demand standard vCPUs", limit=vcpus, need=robots * per_clone))
        elif values.get("max-instances", "").isdigit():
            found.append(Quota(name="running instances", limit=float(values["max-instances"]), need=robots))
        return found

    def _vcpu_quota(self) -> float | None:
        """Service Quotas L-1216C47A (Running On-Demand Standard instances, in vCPUs), if readable."""
        from botocore.exceptions import BotoCoreError, ClientError

        try:
            sq = self.session.client("service-quotas")
            return float(self.api("get service quota", sq.get_service_quota, ServiceCode="ec2",
                                  QuotaCode="L-1216C47A")["Quota"]["Value"])
        except (CcrpError, BotoCoreError, ClientError):
            return None  # no permission, or not offered here: fall back to account attributes


def _backing(image: dict) -> set[str]:
    """The EBS snapshots an AMI is made of."""
    return {m["Ebs"]["SnapshotId"] for m in image.get("BlockDeviceMappings", []) if m.get("Ebs", {}).get("SnapshotId")}
