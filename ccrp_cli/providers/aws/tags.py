"""EC2 tags: the fleet's ownership labels as Tags, TagSpecifications and describe filters."""

from __future__ import annotations

from ..base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, owner_labels


def tags(fleet: str, role: str, robot: str | None = None, name: str | None = None) -> list[dict]:
    labels = owner_labels(fleet, role, robot) | ({"Name": name} if name else {})
    return [{"Key": k, "Value": v} for k, v in labels.items()]


def spec(resource_types: list[str], fleet: str, role: str, robot: str | None = None, name: str | None = None) -> list[dict]:
    """TagSpecifications: tagged atomically at creation, so a crash never leaves an untagged resource."""
    return [{"ResourceType": t, "Tags": tags(fleet, role, robot, name)} for t in resource_types]


def filters(fleet: str, role: str | None = None, robot: str | None = None) -> list[dict]:
    """Most specific first: a describe that tests filters one resource at a time stops at the first
    mismatch (moto does, scanning its whole tag store per tag filter: the robot's tag first keeps a
    robot's lookup in a fleet of N from N times four scans to N)."""
    wanted = {LABEL_ROBOT: robot, LABEL_ROLE: role, LABEL_FLEET: fleet, LABEL_MANAGED: "true"}
    return [{"Name": f"tag:{k}", "Values": [v]} for k, v in wanted.items() if v]


def as_dict(resource: dict) -> dict[str, str]:
    return {t["Key"]: t["Value"] for t in resource.get("Tags") or []}


def owned_by(resource: dict, fleet: str) -> bool:
    t = as_dict(resource)
    return t.get(LABEL_MANAGED) == "true" and t.get(LABEL_FLEET) == fleet
