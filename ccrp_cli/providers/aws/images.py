"""AWS snapshots: AMIs (and the EBS snapshots behind them) of a clone or of the builder, tagged
as the fleet's; Debian's AMI found through its public SSM parameter."""

from __future__ import annotations

from ...errors import CcrpError
from ..base import LABEL_ROBOT, LABEL_ROLE, SnapshotRecord
from . import tags
from .client import AwsClient


def create_snapshot(c: AwsClient, robot: str, name: str) -> SnapshotRecord:
    instances = c.instances(robot, role=None)
    if not instances:
        raise CcrpError(f"robot {robot!r} has no clone to capture", hint=f"ccrp clone create --robot {robot}")
    # A builder's AMI is a build, not a robot's clone: no robot tag, source "build".
    source = robot if tags.as_dict(instances[0]).get(LABEL_ROLE) == "clone" else None
    # AMI names allow letters, digits and ()[] ./-'@_ only.
    ami_name = "".join(c if c.isalnum() or c in "()[] ./-'@_" else "-" for c in name)[:128]
    image_id = c.api(
        "create image", c.ec2.create_image, InstanceId=instances[0]["InstanceId"], Name=ami_name,
        Description=f"ccrp fleet {c.fleet}: " + (f"clone of {robot}" if source else "baked by snapshot bake"),
        TagSpecifications=tags.spec(["image"], c.fleet, "snapshot", source, name=ami_name),
    )["ImageId"]
    # `snapshot bake` deletes the builder right after this returns: wait until the AMI is usable.
    c.api("wait for image", c.ec2.get_waiter("image_available").wait, ImageIds=[image_id],
             WaiterConfig={"Delay": 10, "MaxAttempts": 180})
    image = c.describe("image", [{"Name": "image-id", "Values": [image_id]}])[0]
    # The EBS snapshots get the tags too (gc finds them if their image is ever lost). Tagged
    # afterwards rather than in CreateImage's TagSpecifications, which moto does not model.
    snaps = backing(image)
    if snaps:
        c.api("tag snapshots", c.ec2.create_tags, Resources=sorted(snaps),
                 Tags=tags.tags(c.fleet, "snapshot", source, name=ami_name))
    return snapshot_record(image)


def snapshot_record(image: dict) -> SnapshotRecord:
    gib = sum(m.get("Ebs", {}).get("VolumeSize", 0) for m in image.get("BlockDeviceMappings", []))
    return SnapshotRecord(id=image["ImageId"], name=image.get("Name", ""), created=image.get("CreationDate", "")[:19],
                          source=tags.as_dict(image).get(LABEL_ROBOT) or "build", size_mb=gib * 1024.0 or None)


def list_snapshots(c: AwsClient) -> list[SnapshotRecord]:
    images = c.describe("image", tags.filters(c.fleet, "snapshot"))
    return sorted(map(snapshot_record, images), key=lambda s: s.created)


def resolve_image(c: AwsClient, image: str) -> str:
    """The AMI id an image names: an AMI id as is; an SSM parameter (Debian publishes its current
    AMI as /aws/service/debian/release/bookworm/latest/amd64; EC2's `resolve:ssm:` form too) as
    the id it holds now, so that the fleet's state records which AMI was booted."""
    name = image.removeprefix("resolve:ssm:")
    if not name.startswith("/"):
        return image
    ssm = c.session.client("ssm", config=c.config)
    return c.api(f"get SSM parameter {name}", ssm.get_parameter, Name=name)["Parameter"]["Value"]


def has_image(c: AwsClient, image: str) -> bool:
    key = "image-id" if image.startswith("ami-") else "name"
    return bool(c.api("describe images", c.ec2.describe_images, Filters=[{"Name": key, "Values": [image]}])["Images"])


def delete_snapshot(c: AwsClient, snapshot_id: str) -> None:
    key = "image-id" if snapshot_id.startswith("ami-") else "name"
    found = c.describe("image", tags.filters(c.fleet, "snapshot") + [{"Name": key, "Values": [snapshot_id]}])
    if not found:
        raise CcrpError(f"snapshot {snapshot_id} is not an image of fleet {c.fleet!r}", hint="ccrp snapshot list")
    deregister(c, found[0])


def deregister(c: AwsClient, image: dict) -> None:
    """An AMI and the EBS snapshots CreateImage made of the fleet's clone: they go with it."""
    c.api("deregister image", c.ec2.deregister_image, ImageId=image["ImageId"])
    for snap in sorted(backing(image)):
        c.api("delete snapshot", c.ec2.delete_snapshot, SnapshotId=snap)


def backing(image: dict) -> set[str]:
    """The EBS snapshots an AMI is made of."""
    return {m["Ebs"]["SnapshotId"] for m in image.get("BlockDeviceMappings", []) if m.get("Ebs", {}).get("SnapshotId")}
