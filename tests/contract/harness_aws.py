"""The contract harness on moto (mock_aws): the real boto3 client of AwsProvider, with faults and
delays injected through botocore's own event hooks before a request reaches the fake."""

from __future__ import annotations

import base64
import ipaddress
import threading
import time
from collections import Counter
from contextlib import contextmanager

from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE

from .harness import FLEET
from .specs import FAST, OPERATOR_CIDR, Knobs, clone_spec, inventory

REGION = "us-east-1"
LIVE = ["pending", "running", "stopping", "stopped"]


def _owned_filters(robot: str | None = None) -> list[dict]:
    f = [{"Name": f"tag:{LABEL_MANAGED}", "Values": ["true"]}, {"Name": f"tag:{LABEL_FLEET}", "Values": [FLEET]}]
    return f + ([{"Name": f"tag:{LABEL_ROBOT}", "Values": [robot]}] if robot else [])


class AwsHarness(Knobs):
    kind = "aws"

    def __init__(self, provider, raw) -> None:
        from botocore.awsrequest import AWSResponse

        self.provider, self.raw, self._AWSResponse = provider, raw, AWSResponse
        # The image clones start from: registered in the fake, not the fleet's (no tags), so
        # teardown and gc must leave it alone.
        self.image = raw.register_image(Name="debian-12-amd64", RootDeviceName="/dev/sda1",
                                        Architecture="x86_64")["ImageId"]
        self.calls: Counter = Counter()
        self._lock = threading.Lock()
        self._fraction, self._delay, self._n = 0.0, 0.0, 0
        self._fail_robots: set[str] = set()
        self._doomed: set[str] = set()  # instances whose Elastic IP association will fail
        self._subnets: dict[str, str] = {}
        # moto's backend is not thread-safe (its dicts change size under a concurrent describe):
        # one request at a time inside moto, the injected delay still overlapping outside it, as
        # on EC2. Held from before-call to after-call(-error) by the thread that took it.
        self._moto = threading.Lock()
        self._holding = threading.local()
        self._hook(provider)

    def _hook(self, provider) -> None:
        events = provider.client.ec2.meta.events
        events.register("before-call.ec2", self._before_call)
        events.register("after-call.ec2", self._release)
        events.register("after-call-error.ec2", self._release)
        events.register("after-call.ec2.RunInstances", self._after_run)

    def new_provider(self, inv, workdir):
        """An AwsProvider of another inventory on the same fake, with the same hooks."""
        from ccrp_cli.providers.aws.provider import AwsProvider

        provider = AwsProvider(inv, workdir)
        provider.client.backoff = FAST
        self._hook(provider)
        return provider

    def kill(self, provider_id: str) -> None:
        self.raw.terminate_instances(InstanceIds=[provider_id])  # its Elastic IP stays allocated, as on EC2

    # -- fault injection -------------------------------------------------------------------------
    def _error(self, status: int, code: str, message: str):
        http = self._AWSResponse(f"https://ec2.{REGION}.amazonaws.com/", status, {}, None)
        return http, {"Error": {"Code": code, "Message": message}, "ResponseMetadata": {"HTTPStatusCode": status}}

    def _before_call(self, model, params, **_):
        with self._lock:
            self.calls[model.name] += 1
            self._n += 1
            throttled = int(self._n * self._fraction) > int((self._n - 1) * self._fraction)
        if self._delay:
            time.sleep(self._delay)
        if throttled:
            return self._error(503, "RequestLimitExceeded", "Request limit exceeded.")
        body = params.get("body") or {}
        if model.name == "AssociateAddress" and isinstance(body, dict) and body.get("InstanceId") in self._doomed:
            self._doomed.discard(body["InstanceId"])
            return self._error(403, "UnauthorizedOperation", "You are not authorized to perform this operation.")
        self._moto.acquire()
        self._holding.lock = True
        return None

    def _release(self, **_):
        if getattr(self._holding, "lock", False):
            self._holding.lock = False
            self._moto.release()

    def _after_run(self, parsed, **_):
        for inst in parsed.get("Instances", []):
            robot = {t["Key"]: t["Value"] for t in inst.get("Tags", [])}.get(LABEL_ROBOT)
            if robot in self._fail_robots:
                self._fail_robots.discard(robot)
                self._doomed.add(inst["InstanceId"])

    # -- the fake's contents, read around the provider ---------------------------------------
    def spec(self, robot: str, index: int):
        s = clone_spec(self.provider.inv, robot, index, self.image)
        self._subnets[robot] = s.vpn_subnet
        return s

    def _instances(self, robot: str | None = None) -> list[dict]:
        f = _owned_filters(robot) + [{"Name": "instance-state-name", "Values": LIVE}]
        return [i for r in self.raw.describe_instances(Filters=f)["Reservations"] for i in r["Instances"]]

    def instance_roles(self, robot: str) -> list[str]:
        return [{t["Key"]: t["Value"] for t in i.get("Tags", [])}.get(LABEL_ROLE, "") for i in self._instances(robot)]

    def instances_for(self, robot: str) -> int:
        return len(self._instances(robot))

    def owned_ids(self, robot: str | None = None) -> set[str]:
        r = self.raw
        f = _owned_filters(robot)
        ids = {i["InstanceId"] for i in self._instances(robot)}
        ids |= {a["AllocationId"] for a in r.describe_addresses(Filters=f)["Addresses"]}
        ids |= {v["VolumeId"] for v in r.describe_volumes(Filters=f)["Volumes"]}
        ids |= {i["ImageId"] for i in r.describe_images(Owners=["self"], Filters=f)["Images"]}
        ids |= {s["SnapshotId"] for s in r.describe_snapshots(OwnerIds=["self"], Filters=f)["Snapshots"]}
        # Routes carry no tags: they belong to the fleet's route table, per robot by VPN subnet.
        for rt in r.describe_route_tables(Filters=_owned_filters())["RouteTables"]:
            for route in rt["Routes"]:
                dest = route.get("DestinationCidrBlock")
                if route.get("InstanceId") and (robot is None or dest == self._subnets.get(robot)):
                    ids.add(f"route:{rt['RouteTableId']}:{dest}")
            if robot is None:
                ids.add(rt["RouteTableId"])
        if robot is None:
            ids |= {v["VpcId"] for v in r.describe_vpcs(Filters=f)["Vpcs"]}
            ids |= {s["SubnetId"] for s in r.describe_subnets(Filters=f)["Subnets"]}
            ids |= {g["InternetGatewayId"] for g in r.describe_internet_gateways(Filters=f)["InternetGateways"]}
            ids |= {g["GroupId"] for g in r.describe_security_groups(Filters=f)["SecurityGroups"]}
            ids |= {k["KeyPairId"] for k in r.describe_key_pairs(Filters=f)["KeyPairs"]}
        return ids

    def add_foreign(self) -> str:
        # Named and tagged like robot1's clone, but another fleet's, in the account's default VPC.
        labels = {"Name": "cri-robot1", LABEL_MANAGED: "true", LABEL_FLEET: "other", LABEL_ROLE: "clone", LABEL_ROBOT: "robot1"}
        inst = self.raw.run_instances(ImageId=self.image, InstanceType="t3.micro", MinCount=1, MaxCount=1, TagSpecifications=[
            {"ResourceType": "instance", "Tags": [{"Key": k, "Value": v} for k, v in labels.items()]}])["Instances"][0]
        return inst["InstanceId"]

    def add_leak(self) -> str:
        # An Elastic IP left behind (say, by a crash between allocation and association): idle
        # Elastic IPs are billed, the classic AWS leak.
        labels = {LABEL_MANAGED: "true", LABEL_FLEET: FLEET, LABEL_ROLE: "clone", LABEL_ROBOT: "ghost"}
        return self.raw.allocate_address(Domain="vpc", TagSpecifications=[
            {"ResourceType": "elastic-ip", "Tags": [{"Key": k, "Value": v} for k, v in labels.items()]}])["AllocationId"]

    def exists(self, resource_id: str) -> bool:
        r = self.raw
        if resource_id.startswith("i-"):
            found = [i for res in r.describe_instances(Filters=[{"Name": "instance-id", "Values": [resource_id]}])["Reservations"]
                     for i in res["Instances"]]
            return any(i["State"]["Name"] in LIVE for i in found)
        if resource_id.startswith("eipalloc-"):
            return bool(r.describe_addresses(Filters=[{"Name": "allocation-id", "Values": [resource_id]}])["Addresses"])
        if resource_id.startswith("ami-"):
            return bool(r.describe_images(Filters=[{"Name": "image-id", "Values": [resource_id]}])["Images"])
        if resource_id.startswith("snap-"):
            return bool(r.describe_snapshots(Filters=[{"Name": "snapshot-id", "Values": [resource_id]}])["Snapshots"])
        raise ValueError(f"harness cannot look up {resource_id}")

    def public_ingress(self) -> set[tuple[str, int, str]]:
        common = self.provider.inv.common.cidr
        rules = set()
        for sg in self.raw.describe_security_groups(Filters=_owned_filters())["SecurityGroups"]:
            for perm in sg["IpPermissions"]:
                for rng in perm.get("IpRanges", []):
                    if not ipaddress.ip_network(rng["CidrIp"]).subnet_of(common):
                        rules.add((perm["IpProtocol"], perm.get("FromPort", -1), rng["CidrIp"]))
                for rng in perm.get("Ipv6Ranges", []):
                    rules.add((perm["IpProtocol"], perm.get("FromPort", -1), rng["CidrIpv6"]))
        return rules

    def user_data_sent(self, robot: str) -> bytes:
        inst = self._instances(robot)[0]
        attr = self.raw.describe_instance_attribute(InstanceId=inst["InstanceId"], Attribute="userData")
        return base64.b64decode(attr["UserData"]["Value"])


@contextmanager
def make_harness(tmp_path):
    import boto3
    from moto import mock_aws

    from ccrp_cli.providers.aws.provider import AwsProvider

    inv = inventory({"kind": "aws", "region": REGION, "zones": ["us-east-1a", "us-east-1b"],
                     "instance_type": "t3.medium", "operator_cidr": OPERATOR_CIDR,
                     # the contract proves clones at their own addresses; the gateway: test_aws_provider.py
                     "entry": "per-clone"})
    with mock_aws():
        provider = AwsProvider(inv, tmp_path / "store")
        provider.client.backoff = FAST
        provider.bootstrap()
        yield AwsHarness(provider, boto3.client("ec2", region_name=REGION))
    # mock_aws's exit discards every fake resource: nothing outlives the test.
