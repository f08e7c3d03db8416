"""The fleet's network on AWS, created or reused by bootstrap:

VPC (inventory provider.vpc_id, or an owned one with common.cidr) -> internet gateway -> the
common subnet (common.cidr) -> an owned route table (default route + one route per clone's VPN
subnet) -> the fleet security group -> the operator key pair. Everything created is tagged.
"""

from __future__ import annotations

from dataclasses import dataclass

from ...errors import CcrpError
from ...retry import across_zones
from . import tags
from .client import AwsClient

ROLE = "network"


@dataclass
class Network:
    vpc_id: str
    subnet_id: str
    zone: str
    route_table_id: str
    security_group_id: str
    key_name: str


def _one(items: list[dict]) -> dict | None:
    return items[0] if items else None


def find(c: AwsClient) -> Network | None:
    """The bootstrapped network, looked up by tags (None until bootstrap ran)."""
    f = tags.filters(c.fleet, ROLE)
    subnet = _one(c.api("describe subnets", c.ec2.describe_subnets, Filters=f)["Subnets"])
    rt = _one(c.api("describe route tables", c.ec2.describe_route_tables, Filters=f)["RouteTables"])
    sg = _one(c.api("describe security groups", c.ec2.describe_security_groups, Filters=f)["SecurityGroups"])
    key = _one(c.api("describe key pairs", c.ec2.describe_key_pairs, Filters=f)["KeyPairs"])
    if not (subnet and rt and sg and key):
        return None
    return Network(subnet["VpcId"], subnet["SubnetId"], subnet["AvailabilityZone"], rt["RouteTableId"],
                   sg["GroupId"], key["KeyName"])


def ensure(c: AwsClient, public_key: str) -> Network:
    """Bootstrap: the fleet's network created or reused, and kept for its clones."""
    vpc_id, igw_id = _vpc(c)
    subnet = _subnet(c, vpc_id)
    rt_id = _route_table(c, vpc_id, igw_id, subnet["SubnetId"])
    sg_id = _security_group(c, vpc_id)
    key_name = _key_pair(c, public_key)
    c.net = Network(vpc_id, subnet["SubnetId"], subnet["AvailabilityZone"], rt_id, sg_id, key_name)
    return c.net


def current(c: AwsClient) -> Network:
    """The fleet's network as bootstrap left it (looked up once); refused in one line before."""
    if c.net is None:
        c.net = find(c)
    if c.net is None:
        raise CcrpError(f"fleet {c.fleet!r} has no network on AWS yet", hint="`ccrp fleet up` creates it (bootstrap)")
    return c.net


def _vpc(c: AwsClient) -> tuple[str, str]:
    """(vpc id, internet gateway id): the inventory's VPC, or the fleet's own."""
    vpc_id = c.settings.vpc_id
    if vpc_id:
        found = c.api("describe VPC", c.ec2.describe_vpcs, Filters=[{"Name": "vpc-id", "Values": [vpc_id]}])["Vpcs"]
        if not found:
            raise CcrpError(f"VPC {vpc_id} (inventory provider.vpc_id) not found in {c.settings.region}",
                            hint="check provider.vpc_id and provider.region, or remove vpc_id to let ccrp create one")
    else:
        vpc = _one(c.api("describe VPCs", c.ec2.describe_vpcs, Filters=tags.filters(c.fleet, ROLE))["Vpcs"])
        if vpc is None:
            vpc = c.api("create VPC", c.ec2.create_vpc, CidrBlock=str(c.inv.common.cidr),
                        TagSpecifications=tags.spec(["vpc"], c.fleet, ROLE, name=f"ccrp-{c.fleet}"))["Vpc"]
        vpc_id = vpc["VpcId"]
    attached = c.api("describe internet gateways", c.ec2.describe_internet_gateways,
                     Filters=[{"Name": "attachment.vpc-id", "Values": [vpc_id]}])["InternetGateways"]
    if attached:
        return vpc_id, attached[0]["InternetGatewayId"]
    if c.settings.vpc_id:
        raise CcrpError(f"VPC {vpc_id} has no internet gateway: clones would have no public address",
                        hint="attach an internet gateway to the VPC, or remove provider.vpc_id")
    igw = _one(c.api("describe internet gateways", c.ec2.describe_internet_gateways,
                     Filters=tags.filters(c.fleet, ROLE))["InternetGateways"])
    if igw is None:
        igw = c.api("create internet gateway", c.ec2.create_internet_gateway,
                    TagSpecifications=tags.spec(["internet-gateway"], c.fleet, ROLE))["InternetGateway"]
    c.api("attach internet gateway", c.ec2.attach_internet_gateway, InternetGatewayId=igw["InternetGatewayId"], VpcId=vpc_id)
    return vpc_id, igw["InternetGatewayId"]


def _subnet(c: AwsClient, vpc_id: str) -> dict:
    cidr = str(c.inv.common.cidr)
    in_vpc = c.api("describe subnets", c.ec2.describe_subnets, Filters=[{"Name": "vpc-id", "Values": [vpc_id]}])["Subnets"]
    for subnet in in_vpc:
        if subnet["CidrBlock"] == cidr and tags.owned_by(subnet, c.fleet):
            return subnet
        if subnet["CidrBlock"] == cidr:
            raise CcrpError(f"subnet {subnet['SubnetId']} in {vpc_id} already uses common.cidr {cidr} and is not ccrp's",
                            hint="pick a free common.cidr inside the VPC for the fleet's common network")

    # A subnet lives in one zone; a zone the account cannot use ("Unsupported") moves to the next.
    def create(zone: str) -> dict:
        extra = {"AvailabilityZone": zone} if zone else {}
        return c.api("create subnet", c.ec2.create_subnet, VpcId=vpc_id, CidrBlock=cidr,
                     TagSpecifications=tags.spec(["subnet"], c.fleet, ROLE, name=f"ccrp-{c.fleet}-common"), **extra)["Subnet"]

    return across_zones(c.settings.zones or [""], create, classify=c.classify_error, what="create the common subnet")


def _route_table(c: AwsClient, vpc_id: str, igw_id: str, subnet_id: str) -> str:
    rt = _one(c.api("describe route tables", c.ec2.describe_route_tables, Filters=tags.filters(c.fleet, ROLE))["RouteTables"])
    if rt is None:
        rt = c.api("create route table", c.ec2.create_route_table, VpcId=vpc_id,
                   TagSpecifications=tags.spec(["route-table"], c.fleet, ROLE))["RouteTable"]
    rt_id = rt["RouteTableId"]
    if not any(r.get("DestinationCidrBlock") == "0.0.0.0/0" for r in rt.get("Routes", [])):
        c.api("create default route", c.ec2.create_route, RouteTableId=rt_id, DestinationCidrBlock="0.0.0.0/0", GatewayId=igw_id)
    if not any(a.get("SubnetId") == subnet_id for a in rt.get("Associations", [])):
        c.api("associate route table", c.ec2.associate_route_table, RouteTableId=rt_id, SubnetId=subnet_id)
    return rt_id


def ingress_wanted(c: AwsClient) -> set[tuple[str, int, int, str]]:
    """Public: only the VPN port from anywhere and SSH from the operator; all from the common
    network (topic sharing between clones)."""
    vpn = c.inv.vpn
    return {
        (vpn.proto, vpn.port, vpn.port, "0.0.0.0/0"),
        ("tcp", 22, 22, str(c.settings.operator_cidr)),
        ("-1", -1, -1, str(c.inv.common.cidr)),
    }


def ingress_rules(sg: dict) -> set[tuple[str, int, int, str]]:
    rules = set()
    for perm in sg.get("IpPermissions", []):
        proto = perm["IpProtocol"]
        lo, hi = perm.get("FromPort", -1), perm.get("ToPort", -1)
        if proto == "-1":
            lo = hi = -1
        for r in perm.get("IpRanges", []):
            rules.add((proto, lo, hi, r["CidrIp"]))
        for r in perm.get("Ipv6Ranges", []):
            rules.add((proto, lo, hi, r["CidrIpv6"]))
        for g in perm.get("UserIdGroupPairs", []):
            rules.add((proto, lo, hi, g["GroupId"]))
    return rules


def _permission(rule: tuple[str, int, int, str]) -> dict:
    proto, lo, hi, source = rule
    perm: dict = {"IpProtocol": proto}
    if proto != "-1":
        perm |= {"FromPort": lo, "ToPort": hi}
    if source.startswith("sg-"):
        perm["UserIdGroupPairs"] = [{"GroupId": source}]
    elif ":" in source:
        perm["Ipv6Ranges"] = [{"CidrIpv6": source}]
    else:
        perm["IpRanges"] = [{"CidrIp": source}]
    return perm


def _security_group(c: AwsClient, vpc_id: str) -> str:
    sg = _one(c.api("describe security groups", c.ec2.describe_security_groups, Filters=tags.filters(c.fleet, ROLE))["SecurityGroups"])
    if sg is None:
        created = c.api("create security group", c.ec2.create_security_group, GroupName=f"ccrp-{c.fleet}",
                        Description=f"ccrp fleet {c.fleet}: VPN from anywhere, SSH from the operator",
                        VpcId=vpc_id, TagSpecifications=tags.spec(["security-group"], c.fleet, ROLE))
        sg = {"GroupId": created["GroupId"], "IpPermissions": []}
    # Converge to exactly the wanted rules: a rule someone added by hand is revoked.
    have, want = ingress_rules(sg), ingress_wanted(c)
    if have - want:
        c.api("revoke ingress", c.ec2.revoke_security_group_ingress, GroupId=sg["GroupId"],
              IpPermissions=[_permission(r) for r in sorted(have - want)])
    if want - have:
        c.api("authorize ingress", c.ec2.authorize_security_group_ingress, GroupId=sg["GroupId"],
              IpPermissions=[_permission(r) for r in sorted(want - have)])
    return sg["GroupId"]


def _key_pair(c: AwsClient, public: str) -> str:
    name = f"ccrp-{c.fleet}"
    found = c.api("describe key pairs", c.ec2.describe_key_pairs,
                  Filters=[{"Name": "key-name", "Values": [name]}], IncludePublicKey=True)["KeyPairs"]
    if found:
        key = found[0]
        if not tags.owned_by(key, c.fleet):
            raise CcrpError(f"key pair {name} exists and is not ccrp's", hint="delete or rename it")
        if key.get("PublicKey", "").split()[:2] == public.split()[:2]:
            return name
        # The operator key in the fleet store changed (store recreated): replace the cloud's copy.
        c.api("delete key pair", c.ec2.delete_key_pair, KeyName=name)
    c.api("import key pair", c.ec2.import_key_pair, KeyName=name, PublicKeyMaterial=public.encode(),
          TagSpecifications=tags.spec(["key-pair"], c.fleet, ROLE))
    return name
