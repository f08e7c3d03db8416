"""The AWS backend of the scenarios: moto's server in this process whose EC2 instances really boot
(tests/fakes/aws_boot.py), and `ccrp` as a separate process sent there by AWS_ENDPOINT_URL.

The inventory names no profile and no image: ccrp takes boto3's default chain (the fake
credentials of `env`) and, for `snapshot bake`, the Debian 12 AMI the public SSM parameter names
(the fake publishes it). The common network is a /24 the fake claims on this machine's Docker (so
it overlaps nothing), the operator CIDR is the fake's "internet" (the host's side of it is where
ccrp's SSH comes from); simulated robots sit on that internet (`sim_network`).

The fleet has AWS's default entry, its gateway (provider.entry: gateway), and the region one
Elastic IP (the fake's max_eips), fewer than its clones: the gateway holds it, with its public
subnet (provider.gateway_cidr, a /28 the fake claims too) and the robots dial their ports on it;
the clones have none. The Debian-12 snapshot's builder holds that address while it bakes.

`owned()` lists what moto holds tagged ccrp-fleet=<fleet> that `fleet down` must remove:
instances not terminated, Elastic IPs, volumes, network interfaces, security groups, key pairs,
route tables, subnets, internet gateways, VPCs. AMIs and their EBS snapshots are not listed: they
are the fleet's snapshots, which outlive `fleet down` (`ccrp snapshot delete` removes them).

Faults (each a context manager factory):
- "quota": the account at its instance limit: every RunInstances (or one robot's, if given)
  refused with InstanceLimitExceeded;
- "zone": no capacity in the inventory's first zone (InsufficientInstanceCapacity for instances
  there, Unsupported for a subnet there, so a fresh fleet's subnet goes to the second zone);
- "storm": a fraction of EC2 requests (0.3 unless given) answered 503 RequestLimitExceeded.
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from unittest import mock

from tests.fakes.aws_boot import AwsBoot

from .backend import Backend, inventory_text

REGION = "us-east-1"
ZONES = ["us-east-1a", "us-east-1b"]
COMMON_WITHIN = "10.210.0.0/16"  # the common /24 is the first free one here, the gateway's /28 next
VPN_POOL = "10.215.0.0/16"
INSTANCE_TYPE = "t3.medium"
LIVE = ["pending", "running", "shutting-down", "stopping", "stopped"]

# kind -> (describe call, result key, id field, extra args); all filtered by the fleet's tags.
KINDS = {
    "instance": ("describe_instances", "Reservations", "InstanceId",
                 {"Filters": [{"Name": "instance-state-name", "Values": LIVE}]}),
    "elastic_ip": ("describe_addresses", "Addresses", "AllocationId", {}),
    "volume": ("describe_volumes", "Volumes", "VolumeId", {}),
    "network_interface": ("describe_network_interfaces", "NetworkInterfaces", "NetworkInterfaceId", {}),
    "security_group": ("describe_security_groups", "SecurityGroups", "GroupId", {}),
    "key_pair": ("describe_key_pairs", "KeyPairs", "KeyName", {}),
    "route_table": ("describe_route_tables", "RouteTables", "RouteTableId", {}),
    "subnet": ("describe_subnets", "Subnets", "SubnetId", {}),
    "internet_gateway": ("describe_internet_gateways", "InternetGateways", "InternetGatewayId", {}),
    "vpc": ("describe_vpcs", "Vpcs", "VpcId", {}),
}


@dataclass
class AwsBackend(Backend):
    fake: AwsBoot | None = None  # the booting moto (its containers, calls, faults, Debian AMI)


def owned_by_fleet(fake: AwsBoot, fleet: str) -> list[str]:
    """"kind id" of everything moto holds tagged ccrp-fleet=<fleet> (snapshots excepted)."""
    ec2 = fake.client()
    fleet_tag = [{"Name": "tag:ccrp-fleet", "Values": [fleet]}]
    found = []
    for kind, (op, key, id_field, extra) in KINDS.items():
        args = dict(extra)
        args["Filters"] = fleet_tag + args.get("Filters", [])
        items = getattr(ec2, op)(**args)[key]
        if kind == "instance":
            items = [i for r in items for i in r["Instances"]]
        found += [f"{kind} {item[id_field]}" for item in items]
    return sorted(found)


@contextmanager
def open_backend(tmp_path: Path, fleet: str):
    tmp_path = Path(tmp_path)
    home = tmp_path / "ccrp-home"
    home.mkdir(parents=True, exist_ok=True)
    # The user's shell: nothing of this machine's AWS setup (a profile would win over the fake's keys).
    with mock.patch.dict(os.environ):  # restored on exit
        for var in ("AWS_PROFILE", "AWS_DEFAULT_PROFILE", "AWS_SESSION_TOKEN", "AWS_SECURITY_TOKEN"):
            os.environ.pop(var, None)
        with AwsBoot(region=REGION) as fake:
            yield _backend(tmp_path, fleet, home, fake)


def _backend(tmp_path: Path, fleet: str, home: Path, fake: AwsBoot) -> AwsBackend:
    common = fake.claim_subnet_cidr(COMMON_WITHIN)
    gateway_cidr = fake.claim_subnet_cidr(COMMON_WITHIN, prefix=28)
    fake.max_eips = 1
    provider = (f"  kind: aws\n  region: {REGION}\n  instance_type: {INSTANCE_TYPE}\n"
                f"  zones: [{', '.join(ZONES)}]\n  operator_cidr: {fake.internet_cidr}\n"
                f"  gateway_cidr: {gateway_cidr}\n")
    inventory = tmp_path / f"{fleet}.yaml"
    inventory.write_text(inventory_text(fleet, provider, common, VPN_POOL))
    faults = {
        "quota": lambda robot=None: fake.refuse_robot(robot),
        "zone": lambda zone=ZONES[0]: fake.no_capacity(zone),
        "storm": lambda fraction=0.3: fake.throttle(fraction),
    }
    return AwsBackend(kind="aws", inventory=inventory, home=home, env=fake.env(),
                      owned=lambda: owned_by_fleet(fake, fleet), faults=faults,
                      sim_network=fake.internet_network, fake=fake, labels=[f"ccrp-fake={fake.boot.run}"],
                      gateway=lambda: _delete_gateway(fake, fleet))


def _delete_gateway(fake: AwsBoot, fleet: str) -> str:
    """What an operator's `aws ec2 terminate-instances` of the fleet's gateway does; its address
    (the Elastic IP, which stays), for the test to compare."""
    ec2 = fake.client()
    [gateway] = [i for r in ec2.describe_instances(Filters=[
        {"Name": "tag:ccrp-fleet", "Values": [fleet]}, {"Name": "tag:ccrp-role", "Values": ["gateway"]},
        {"Name": "instance-state-name", "Values": ["pending", "running", "stopping", "stopped"]}])["Reservations"]
        for i in r["Instances"]]
    ec2.terminate_instances(InstanceIds=[gateway["InstanceId"]])
    ec2.get_waiter("instance_terminated").wait(InstanceIds=[gateway["InstanceId"]], WaiterConfig={"Delay": 1, "MaxAttempts": 120})
    return gateway["PublicIpAddress"]
