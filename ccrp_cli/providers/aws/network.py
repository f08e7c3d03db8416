"""The fleet's network on AWS, created or reused by bootstrap:

VPC (inventory provider.vpc_id, or an owned one with common.cidr) -> internet gateway -> the
common subnet (common.cidr) -> an owned route table (default route + one route per clone's VPN
subnet) -> the fleet security group -> the operator key pair. Everything created is tagged.

Behind an entry gateway (provider.entry: gateway, docs/aws.md) the clones have no public address,
and on EC2 an instance without one cannot use the internet gateway: the gateway is their NAT
instance. It cannot sit in the clones' subnet (its own packets out would follow their default
route back to itself), so it has two legs: its primary interface, holding the fleet's Elastic IP,
in a small public subnet (provider.gateway_cidr, its own route table to the internet gateway,
its own security group: the robots' ports, SSH from the operator), and a second interface at
gateway_ip in the clones' subnet, whose default route provider.py points at that interface once
the gateway exists (until then it is the internet gateway, which nothing there can use).
"""

from __future__ import annotations

import ipaddress
import time

from ...errors import CcrpError
from ...models.addressing import capacity
from ...retry import across_zones
from ..base import GATEWAY_ROLE
from . import tags
from .client import AwsClient, Network

ROLE = "network"


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
    g = tags.filters(c.fleet, GATEWAY_ROLE)
    gw_subnet = _one(c.api("describe subnets", c.ec2.describe_subnets, Filters=g)["Subnets"])
    gw_sg = _one(c.api("describe security groups", c.ec2.describe_security_groups, Filters=g)["SecurityGroups"])
    return Network(subnet["VpcId"], subnet["SubnetId"], subnet["AvailabilityZone"], rt["RouteTableId"],
                   sg["GroupId"], key["KeyName"], gw_subnet["SubnetId"] if gw_subnet else None,
                   gw_sg["GroupId"] if gw_sg else None)


def ensure(c: AwsClient, public_key: str) -> Network:
    """Bootstrap: the fleet's network created or reused, and kept for its clones."""
    vpc_id, igw_id = _vpc(c)
    subnet = _subnet(c, vpc_id)
    gateway = c.settings.entry == "gateway"
    # Behind a gateway, the clones' default route is the gateway's once it exists (provider.py).
    rt_id = _route_table(c, vpc_id, igw_id, subnet["SubnetId"], ROLE, replace=not gateway)
    sg_id = _security_group(c, vpc_id, ROLE, f"ccrp-{c.fleet}", "clones", ingress_wanted(c))
    key_name = _key_pair(c, public_key)
    gw_subnet = gw_sg = None
    if gateway:
        gw_subnet = _gateway_subnet(c, vpc_id, subnet["AvailabilityZone"])
        _route_table(c, vpc_id, igw_id, gw_subnet, GATEWAY_ROLE, replace=True)
        gw_sg = _security_group(c, vpc_id, GATEWAY_ROLE, f"ccrp-{c.fleet}-gateway", "entry gateway",
                                gateway_ingress_wanted(c))
    c.net = Network(vpc_id, subnet["SubnetId"], subnet["AvailabilityZone"], rt_id, sg_id, key_name, gw_subnet, gw_sg)
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


def _gateway_subnet(c: AwsClient, vpc_id: str, zone: str) -> str:
    """The entry gateway's public subnet (provider.gateway_cidr), in the clones' subnet's zone: an
    instance's interfaces are all in one zone. A CIDR outside the VPC's blocks is added to it."""
    found = _one(c.api("describe subnets", c.ec2.describe_subnets, Filters=tags.filters(c.fleet, GATEWAY_ROLE))["Subnets"])
    if found:
        return found["SubnetId"]
    cidr = c.settings.gateway_cidr
    for _ in range(30):  # an added block is "associating" for a moment, and takes no subnet until it is not
        vpc = c.api("describe VPC", c.ec2.describe_vpcs, VpcIds=[vpc_id])["Vpcs"][0]
        blocks = {ipaddress.IPv4Network(a["CidrBlock"]): a["CidrBlockState"]["State"]
                  for a in vpc.get("CidrBlockAssociationSet", []) if a["CidrBlockState"]["State"] in ("associated", "associating")}
        within = [state for block, state in blocks.items() if cidr.subnet_of(block)]
        if not within:
            c.api("add provider.gateway_cidr to the VPC", c.ec2.associate_vpc_cidr_block, VpcId=vpc_id, CidrBlock=str(cidr))
        elif "associated" in within:
            break
        time.sleep(2)
    return c.api("create the gateway's subnet", c.ec2.create_subnet, VpcId=vpc_id, CidrBlock=str(cidr), AvailabilityZone=zone,
                 TagSpecifications=tags.spec(["subnet"], c.fleet, GATEWAY_ROLE, name=f"ccrp-{c.fleet}-gateway"))["Subnet"]["SubnetId"]


def _route_table(c: AwsClient, vpc_id: str, igw_id: str, subnet_id: str, role: str, replace: bool) -> str:
    """The subnet's route table of `role`, with a default route to the internet gateway (one that
    leads elsewhere is left alone unless `replace`)."""
    rt = _one(c.api("describe route tables", c.ec2.describe_route_tables, Filters=tags.filters(c.fleet, role))["RouteTables"])
    if rt is None:
        rt = c.api("create route table", c.ec2.create_route_table, VpcId=vpc_id,
                   TagSpecifications=tags.spec(["route-table"], c.fleet, role))["RouteTable"]
    rt_id = rt["RouteTableId"]
    default = next((r for r in rt.get("Routes", []) if r.get("DestinationCidrBlock") == "0.0.0.0/0"), None)
    if default is None:
        c.api("create default route", c.ec2.create_route, RouteTableId=rt_id, DestinationCidrBlock="0.0.0.0/0", GatewayId=igw_id)
    elif replace and default.get("GatewayId") != igw_id:  # the fleet's entry went back to per-clone
        c.api("replace default route", c.ec2.replace_route, RouteTableId=rt_id, DestinationCidrBlock="0.0.0.0/0", GatewayId=igw_id)
    if not any(a.get("SubnetId") == subnet_id for a in rt.get("Associations", [])):
        c.api("associate route table", c.ec2.associate_route_table, RouteTableId=rt_id, SubnetId=subnet_id)
    return rt_id


def ingress_wanted(c: AwsClient) -> set[tuple[str, int, int, str]]:
    """The clones' group: all from the common network (topic sharing between clones; behind an
    entry gateway, also the gateway's leg there: the robots' VPN packets and ccrp's SSH); in a
    per-clone fleet, the VPN port from anywhere and SSH from the operator too."""
    vpn = c.inv.vpn
    common = {("-1", -1, -1, str(c.inv.common.cidr))}
    if c.settings.entry == "gateway":
        return common
    return common | {(vpn.proto, vpn.port, vpn.port, "0.0.0.0/0"), ("tcp", 22, 22, str(c.settings.operator_cidr))}


def gateway_ingress_wanted(c: AwsClient) -> set[tuple[str, int, int, str]]:
    """The entry gateway's public leg: the robots' ports (render/gateway.py, models/addressing.py
    entry_port) from anywhere, SSH from the operator; nothing else."""
    vpn = c.inv.vpn
    return {(vpn.proto, vpn.port + 1, vpn.port + capacity(c.inv), "0.0.0.0/0"), ("tcp", 22, 22, str(c.settings.operator_cidr))}


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


def _security_group(c: AwsClient, vpc_id: str, role: str, name: str, what: str, want: set[tuple[str, int, int, str]]) -> str:
    sg = _one(c.api("describe security groups", c.ec2.describe_security_groups, Filters=tags.filters(c.fleet, role))["SecurityGroups"])
    if sg is None:
        created = c.api("create security group", c.ec2.create_security_group, GroupName=name,
                        Description=f"ccrp fleet {c.fleet}: {what}",
                        VpcId=vpc_id, TagSpecifications=tags.spec(["security-group"], c.fleet, role))
        sg = {"GroupId": created["GroupId"], "IpPermissions": []}
    # Converge to exactly the wanted rules: a rule someone added by hand is revoked.
    have = ingress_rules(sg)
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
