"""The AWS backend's client: the boto3 session and EC2 client (botocore's own retries off, so
that backoff lives in one place: retry.call, with errors.py's classification), SDK errors turned
into one-line CcrpErrors, and the tagged lookups the other modules of the backend share."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import cast

from ...errors import CcrpError, translated
from ...models.inventory import Inventory
from ...retry import Backoff, call
from . import tags
from .errors import INSTALL_HINT, as_ccrp, classify
from .settings import AwsSettings

LIVE = ["pending", "running", "stopping", "stopped"]

# kind -> (describe call, result key, id filter, id field, extra describe args)
KINDS: dict[str, tuple[str, str, str, str, dict]] = {
    "instance": ("describe_instances", "Reservations", "instance-id", "InstanceId",
                 {"Filters": [{"Name": "instance-state-name", "Values": LIVE}]}),
    "elastic_ip": ("describe_addresses", "Addresses", "allocation-id", "AllocationId", {}),
    "volume": ("describe_volumes", "Volumes", "volume-id", "VolumeId", {}),
    "image": ("describe_images", "Images", "image-id", "ImageId", {"Owners": ["self"]}),
    "snapshot": ("describe_snapshots", "Snapshots", "snapshot-id", "SnapshotId", {"OwnerIds": ["self"]}),
    "network_interface": ("describe_network_interfaces", "NetworkInterfaces", "network-interface-id", "NetworkInterfaceId", {}),
    "security_group": ("describe_security_groups", "SecurityGroups", "group-id", "GroupId", {}),
    "key_pair": ("describe_key_pairs", "KeyPairs", "key-pair-id", "KeyPairId", {}),
    "route_table": ("describe_route_tables", "RouteTables", "route-table-id", "RouteTableId", {}),
    "subnet": ("describe_subnets", "Subnets", "subnet-id", "SubnetId", {}),
    "internet_gateway": ("describe_internet_gateways", "InternetGateways", "internet-gateway-id", "InternetGatewayId", {}),
    "vpc": ("describe_vpcs", "Vpcs", "vpc-id", "VpcId", {}),
}


@dataclass
class Network:
    """The fleet's network as bootstrap made or found it (network.py), kept by the client."""

    vpc_id: str
    subnet_id: str
    zone: str
    route_table_id: str
    security_group_id: str
    key_name: str
    # Behind an entry gateway: its public subnet and security group (None in a per-clone fleet).
    gateway_subnet_id: str | None = None
    gateway_group_id: str | None = None


class AwsClient:
    backoff = Backoff()

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        try:
            import boto3
            from botocore.config import Config
            from botocore.exceptions import BotoCoreError
        except ImportError:
            raise CcrpError("the AWS SDK (boto3) is not installed", hint=INSTALL_HINT) from None
        self.inv, self.fleet, self.workdir = inv, inv.fleet, Path(workdir)
        self.settings = cast(AwsSettings, inv.provider)  # get_provider picked this backend by these settings' kind
        try:
            self.session = boto3.Session(profile_name=self.settings.profile, region_name=self.settings.region)
        except BotoCoreError as exc:  # unknown profile
            raise as_ccrp("session", exc) from exc
        # retry.call is the one place for retries: botocore's own are off.
        self.config = config = Config(retries={"total_max_attempts": 1}, connect_timeout=10, read_timeout=60)
        self.ec2 = self.session.client("ec2", config=config)
        self.net: Network | None = None  # the fleet's network, once bootstrapped or found

    # -- errors and retries ----------------------------------------------------------------------
    def classify_error(self, exc: BaseException):
        return classify(exc)

    def api(self, what: str, fn, *args, **kwargs):
        """Every SDK call goes through here: retried on throttling / 5xx, and SDK errors turned into
        one-line CcrpErrors (cause kept)."""
        from botocore.exceptions import BotoCoreError, ClientError

        sdk = (BotoCoreError, ClientError)
        with translated(what, lambda w, exc: as_ccrp(w, exc) if isinstance(exc, sdk) else None):
            return call(fn, *args, classify=self.classify_error, what=what, backoff=self.backoff, **kwargs)

    def wait(self, waiter: str, ids: list[str]) -> None:
        w = self.ec2.get_waiter(waiter)
        self.api(waiter.replace("_", " "), w.wait, InstanceIds=ids, WaiterConfig={"Delay": 3, "MaxAttempts": 100})

    # -- lookups -----------------------------------------------------------------------------
    def describe(self, kind: str, filters: list[dict]) -> list[dict]:
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

    def instances(self, robot: str | None = None, role: str | None = "clone", states: list[str] = LIVE) -> list[dict]:
        return self.describe("instance", tags.filters(self.fleet, role, robot) + [{"Name": "instance-state-name", "Values": states}])

    # -- what ending an instance takes: its routes, then the instance ------------------------------
    def unroute(self, instance_ids: list[str]) -> None:
        """Delete the routes in the fleet's route tables that lead to these instances."""
        for rt in self.describe("route_table", tags.filters(self.fleet)):
            for r in rt["Routes"]:
                if r.get("InstanceId") in instance_ids and r.get("DestinationCidrBlock"):
                    self.api("delete route", self.ec2.delete_route, RouteTableId=rt["RouteTableId"],
                             DestinationCidrBlock=r["DestinationCidrBlock"])

    def terminate_ids(self, ids: list[str]) -> None:
        self.unroute(ids)
        self.api("terminate instances", self.ec2.terminate_instances, InstanceIds=ids)

    def release(self, eip: dict) -> None:
        current = self.api("describe Elastic IP", self.ec2.describe_addresses, AllocationIds=[eip["AllocationId"]])["Addresses"]
        if current and current[0].get("AssociationId"):
            self.api("disassociate Elastic IP", self.ec2.disassociate_address, AssociationId=current[0]["AssociationId"])
        self.api("release Elastic IP", self.ec2.release_address, AllocationId=eip["AllocationId"])
