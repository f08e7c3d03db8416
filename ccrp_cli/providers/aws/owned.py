"""AWS: everything tagged with the fleet (what `ccrp gc` sees), deleting it after checking its
tags again, and `fleet down`'s teardown in dependency order."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_ROBOT, OwnedResource, Role, with_roles
from . import images, tags
from .client import KINDS, AwsClient

# Teardown order: what depends on something is removed before it. Snapshots outlive the fleet
# (as on Docker): `ccrp snapshot delete` removes them.
TEARDOWN = ["instance", "elastic_ip", "volume", "network_interface", "security_group", "key_pair", "route_table", "subnet",
            "internet_gateway", "vpc"]
# What each kind is to the fleet (`ccrp gc`); Elastic IPs, volumes, interfaces and EBS snapshots
# belong to a robot. The entry gateway's instance, interfaces and Elastic IP carry its robot label
# (base.GATEWAY: Role.GATEWAY, kept while the state records the gateway); its subnet, route table
# and security group are made by bootstrap, as the clones' are.
ROLES = {"instance": Role.CLONE, "image": Role.IMAGE, "security_group": Role.BOOTSTRAP, "key_pair": Role.BOOTSTRAP,
         "route_table": Role.BOOTSTRAP, "subnet": Role.BOOTSTRAP, "internet_gateway": Role.BOOTSTRAP,
         "vpc": Role.BOOTSTRAP}


def list_owned(c: AwsClient) -> list[OwnedResource]:
    owned: list[OwnedResource] = []
    backing: set[str] = set()  # EBS snapshots of an owned image go with their image
    for kind in KINDS:
        for item in c.describe(kind, tags.filters(c.fleet)):
            if kind == "image":
                backing |= images.backing(item)
            rid = item[KINDS[kind][3]]
            if kind == "snapshot" and rid in backing:
                continue
            t = tags.as_dict(item)
            name = t.get("Name") or item.get("GroupName") or item.get("KeyName") or item.get("PublicIp") or ""
            owned.append(OwnedResource(kind=kind, id=rid, name=name, robot=t.get(LABEL_ROBOT)))
    return with_roles(owned, ROLES)


def delete_owned(c: AwsClient, resource: OwnedResource) -> None:
    if not delete(c, resource.kind, resource.id):
        raise CcrpError(f"{resource.kind} {resource.id} is not owned by fleet {c.fleet!r} (or is gone)")


def delete(c: AwsClient, kind: str, rid: str) -> bool:
    """Delete one resource after checking, again, that it carries the fleet's tags.
    False when there is no such owned resource (never touched)."""
    if kind not in KINDS:
        raise CcrpError(f"unknown AWS resource kind {kind!r}")
    found = c.describe(kind, tags.filters(c.fleet) + [{"Name": KINDS[kind][2], "Values": [rid]}])
    if not found:
        return False
    item, ec2 = found[0], c.ec2
    if kind == "instance":
        c.terminate_ids([rid])
    elif kind == "elastic_ip":
        c.release(item)
    elif kind == "volume" and item["State"] != "available":
        if item["State"] != "in-use":
            return False  # deleting with its terminated instance
        raise CcrpError(f"volume {rid} is attached to an instance", hint="delete the instance first")
    elif kind == "image":
        c.api("deregister image", ec2.deregister_image, ImageId=rid)
        # Its EBS snapshots were made by CreateImage from the fleet's clone: they go with it.
        for snap in sorted(images.backing(item)):
            c.api("delete snapshot", ec2.delete_snapshot, SnapshotId=snap)
    elif kind == "route_table":
        for a in item.get("Associations", []):
            if not a.get("Main"):
                c.api("disassociate route table", ec2.disassociate_route_table, AssociationId=a["RouteTableAssociationId"])
        c.api("delete route table", ec2.delete_route_table, RouteTableId=rid)
    elif kind == "internet_gateway":
        for a in item.get("Attachments", []):
            c.api("detach internet gateway", ec2.detach_internet_gateway, InternetGatewayId=rid, VpcId=a["VpcId"])
        c.api("delete internet gateway", ec2.delete_internet_gateway, InternetGatewayId=rid)
    else:
        op, arg = {"volume": ("delete_volume", "VolumeId"), "snapshot": ("delete_snapshot", "SnapshotId"),
                   "security_group": ("delete_security_group", "GroupId"), "key_pair": ("delete_key_pair", "KeyName"),
                   "subnet": ("delete_subnet", "SubnetId"), "vpc": ("delete_vpc", "VpcId"),
                   "network_interface": ("delete_network_interface", "NetworkInterfaceId")}[kind]
        c.api(op.replace("_", " "), getattr(ec2, op), **{arg: item["KeyName"] if kind == "key_pair" else rid})
    return True


def teardown(c: AwsClient) -> list[str]:
    """Everything the fleet owns except its snapshots, dependents first."""
    owned = sorted((r for r in list_owned(c) if r.kind in TEARDOWN), key=lambda r: TEARDOWN.index(r.kind))
    removed: list[str] = []
    instances = [r.id for r in owned if r.kind == "instance"]
    if instances:
        c.terminate_ids(instances)
        # Security groups, subnets and volumes stay in use until the instances are really gone.
        c.wait("instance_terminated", instances)
        removed += [f"instance {r.name or r.id}" for r in owned if r.kind == "instance"]
    for r in owned:
        if r.kind != "instance" and delete(c, r.kind, r.id):
            removed.append(f"{r.kind} {r.name or r.id}")
    c.net = None
    return removed


def leftovers(c: AwsClient) -> list[str]:
    return [f"{r.kind} {r.name or r.id}" for r in list_owned(c) if r.kind in TEARDOWN]
