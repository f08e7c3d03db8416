"""The fleet's network on AWS, created or reused by bootstrap:

VPC (inventory provider.vpc_id, or an owned one with common.cidr) -> internet gateway -> the
common subnet (common.cidr) -> an owned route table (default route + one route per clone's VPN
subnet) -> the fleet security group -> the operator key pair. Everything created is tagged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from ...errors import CcrpError
from ...retry import across_zones
from . import tags

if TYPE_CHECKING:
    from .provider import AwsProvider

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


def find(p: "AwsProvider") -> Network | None:
    """The bootstrapped network, looked up by tags (None until bootstrap ran)."""
    f = tags.filters(p.fleet, ROLE)
    subnet = _one(p.api("describe subnets", p.ec2.describe_subnets, Filters=f)["Subnets"])
    rt = _one(p.api("describe route tables", p.ec2.describe_route_tables, Filters=f)["RouteTables"])
    sg = _one(p.api("describe security groups", p.ec2.describe_security_groups, Filters=f)["SecurityGroups"])
    key = _one(p.api("describe key pairs", p.ec2.describe_key_pairs, Filters=f)["KeyPairs"])
    if not (subnet and rt and sg and key):
        return None
    return Network(subnet["VpcId"], subnet["SubnetId"], subnet["AvailabilityZone"], rt["RouteTableId"],
                   sg["GroupId"], key["KeyName"])


def ensure(p: "AwsProvider") -> Network:
    vpc_id, igw_id = _vpc(p)
    subnet = _subnet(p, vpc_id)
    rt_id = _route_table(p, vpc_id, igw_id, subnet["SubnetId"])
    sg_id = _security_group(p, vpc_id)
    key_name = _key_pair(p)
    return Network(vpc_id, subnet["SubnetId"], subnet["AvailabilityZone"], rt_id, sg_id, key_name)


def _vpc(p: "AwsProvider") -> tuple[str, str]:
    """(vpc id, internet gateway id): the inventory's VPC, or the fleet's own."""
    vpc_id = p.settings.vpc_id
    if vpc_id:
        found = p.api("describe VPC", p.ec2.describe_vpcs, Filters=[{"Name": "vpc-id", "Values": [vpc_id]}])["Vpcs"]
        if not found:
            raise CcrpError(f"VPC {vpc_id} (inventory provider.vpc_id) not found in {p.settings.region}",
                            hint="check provider.vpc_id and provider.region, or remove vpc_id to let ccrp create one")
    else:
        vpc = _one(p.api("describe VPCs", p.ec2.describe_vpcs, Filters=tags.filters(p.fleet, ROLE))["Vpcs"])
        if vpc is None:
            vpc = p.api("create VPC", p.ec2.create_vpc, CidrBlock=str(p.inv.common.cidr),
                        TagSpecifications=tags.spec(["vpc"], p.fleet, ROLE, name=f"ccrp-{p.fleet}"))["Vpc"]
        vpc_id = vpc["VpcId"]
    attached = p.api("describe internet gateways", p.ec2.describe_internet_gateways,
                     Filters=[{"Name": "attachment.vpc-id", "Values": [vpc_id]}])["InternetGateways"]
    if attached:
        return vpc_id, attached[0]["InternetGatewayId"]
    if p.settings.vpc_id:
        raise CcrpError(f"VPC {vpc_id} has no internet gateway: clones would have no public address",
                        hint="attach an internet gateway to the VPC, or remove provider.vpc_id")
    igw = _one(p.api("describe internet gateways", p.ec2.describe_internet_gateways,
                     Filters=tags.filters(p.fleet, ROLE))["InternetGateways"])
    if igw is None:
        igw = p.api("create internet gateway", p.ec2.create_internet_gateway,
                    TagSpecifications=tags.spec(["internet-gateway"], p.fleet, ROLE))["InternetGateway"]
    p.api("attach internet gateway", p.ec2.attach_internet_gateway, InternetGatewayId=igw["InternetGatewayId"], VpcId=vpc_id)
    return vpc_id, igw["InternetGatewayId"]


def _subnet(p: "AwsProvider", vpc_id: str) -> dict:
    cidr = str(p.inv.common.cidr)
    in_vpc = p.api("describe subnets", p.ec2.describe_subnets, Filters=[{"Name": "vpc-id", "Values": [vpc_id]}])["Subnets"]
    for subnet in in_vpc:
        if subnet["CidrBlock"] == cidr and tags.owned_by(subnet, p.fleet):
            return subnet
        if subnet["CidrBlock"] == cidr:
            raise CcrpError(f"subnet {subnet['SubnetId']} in {vpc_id} already uses common.cidr {cidr} and is not ccrp's",
                            hint="pick a free common.cidr inside the VPC for the fleet's common network")

    # A subnet lives in one zone; a zone the account cannot use ("Unsupported") moves to the next.
    def create(zone: str) -> dict:
        extra = {"AvailabilityZone": zone} if zone else {}
        return p.api("create subnet", p.ec2.create_subnet, VpcId=vpc_id, CidrBlock=cidr,
                     TagSpecifications=tags.spec(["subnet"], p.fleet, ROLE, name=f"ccrp-{p.fleet}-common"), **extra)["Subnet"]

    return across_zones(p.settings.zones or [""], create, classify=p.classify_error, what="create the common subnet")


def _route_table(p: "AwsProvider", vpc_id: str, igw_id: str, subnet_id: str) -> str:
    rt = _one(p.api("describe route tables", p.ec2.describe_route_tables, Filters=tags.filters(p.fleet, ROLE))["RouteTables"])
    if rt is None:
        rt = p.api("create route table", p.ec2.create_route_table, VpcId=vpc_id,
                   TagSpecifications=tags.spec(["route-table"], p.fleet, ROLE))["RouteTable"]
    rt_id = rt["RouteTableId"]
    if not any(r.get("DestinationCidrBlock") == "0.0.0.0/0" for r in rt.get("Routes", [])):
        p.api("create default route", p.ec2.create_route, RouteTableId=rt_id, DestinationCidrBlock="0.0.0.0/0", GatewayId=igw_id)
    if not any(a.get("SubnetId") == subnet_id for a in rt.get("Associations", [])):
        p.api("associate route table", p.ec2.associate_route_table, RouteTableId=rt_id, SubnetId=subnet_id)
    return rt_id


def ingress_wanted(p: "AwsProvider") -> set[tuple[str, int, int, str]]:
    """Public: only the VPN port from anywhere and SSH from the operator; all from the common
    network (topic sharing between clones)."""
    vpn = p.inv.vpn
    return {
        (vpn.proto, vpn.port, vpn.port, "0.0.0.0/0"),
        ("tcp", 22, 22, str(p.settings.operator_cidr)),
        ("-1", -1, -1, str(p.inv.common.cidr)),
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


def _security_group(p: "AwsProvider", vpc_id: str) -> str:
    sg = _one(p.api("describe security groups", p.ec2.describe_security_groups, Filters=tags.filters(p.fleet, ROLE))["SecurityGroups"])
    if sg is None:
        created = p.api("create security group", p.ec2.create_security_group, GroupName=f"ccrp-{p.fleet}",
                        Description=f"ccrp fleet {p.fleet}: VPN from anywhere, SSH from the operator",
                        VpcId=vpc_id, TagSpecifications=tags.spec(["security-group"], p.fleet, ROLE))
        sg = {"GroupId": created["GroupId"], "IpPermissions": []}
    # Converge to exactly the wanted rules: a rule someone added by hand is revoked.
    have, want = ingress_rules(sg), ingress_wanted(p)
    if have - want:
        p.api("revoke ingress", p.ec2.revoke_security_group_ingress, GroupId=sg["GroupId"],
              IpPermissions=[_permission(r) for r in sorted(have - want)])
    if want - have:
        p.api("authorize ingress", p.ec2.authorize_security_group_ingress, GroupId=sg["GroupId"],
              IpPermissions=[_permission(r) for r in sorted(want - have)])
    return sg["GroupId"]


def _key_pair(p: "AwsProvider") -> str:
    name, public = f"ccrp-{p.fleet}", p.operator_public_key()
    found = p.api("describe key pairs", p.ec2.describe_key_pairs,
                  Filters=[{"Name": "key-name", "Values": [name]}], IncludePublicKey=True)["KeyPairs"]
    if found:
        key = found[0]
        if not tags.owned_by(key, p.fleet):
            raise CcrpError(f"key pair {name} exists and is not ccrp's", hint="delete or rename it")
        if key.get("PublicKey", "").split()[:2] == public.split()[:2]:
            return name
        # The operator key in the fleet store changed (store recreated): replace the cloud's copy.
        p.api("delete key pair", p.ec2.delete_key_pair, KeyName=name)
    p.api("import key pair", p.ec2.import_key_pair, KeyName=name, PublicKeyMaterial=public.encode(),
          TagSpecifications=tags.spec(["key-pair"], p.fleet, ROLE))
    return name
