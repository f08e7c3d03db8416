"""GCE names and ownership marks.

Instances, disks and images carry the fleet's labels (base.owner_labels). Networks, subnetworks,
firewall rules and routes cannot be labelled in the v1 API: ccrp owns one of those only when its
name starts with `ccrp-<fleet>-` AND its description is the ownership line written by `describe`
(fleet names contain no '-', so one fleet's prefix never matches another's). Reserved addresses
could carry labels but are owned by that same name-and-description rule, as routes are, so that
a clone's regional leftovers are recognised by one check.
"""

from __future__ import annotations

import hashlib
import re
import uuid

from ..base import GATEWAY, LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, owner_labels

MAX_NAME = 63  # GCE names: [a-z]([-a-z0-9]{0,61}[a-z0-9])?
_INVALID = re.compile(r"[^a-z0-9-]+")
_DESCRIPTION = "ccrp:"
# Request ids must be UUIDs; uuid5 under this namespace makes them a pure function of their input.
_REQUEST_NS = uuid.UUID("6f1c8f0e-4c7b-5d43-9a55-2c9a0f3d7e11")


def gce_name(text: str) -> str:
    """text as a valid GCE name; over-long names keep their head (the ownership prefix) and end in a
    hash of the whole, so two long names never collide."""
    name = re.sub("-+", "-", _INVALID.sub("-", text.lower())).strip("-")
    if len(name) > MAX_NAME:
        digest = hashlib.sha256(name.encode()).hexdigest()[:8]
        name = f"{name[:MAX_NAME - 9].rstrip('-')}-{digest}"
    return name


def request_id(*parts: str) -> str:
    """A deterministic requestId: a retried insert is recognised by GCE and not executed twice."""
    return str(uuid.uuid5(_REQUEST_NS, "/".join(parts)))


def tail(link: str) -> str:
    """Last segment of a resource URL ("…/zones/europe-west2-a" -> "europe-west2-a")."""
    return link.rstrip("/").rsplit("/", 1)[-1]


def same_resource(a: str, b: str) -> bool:
    """Full and partial URLs of one resource compare equal (projects/…/zones/…/instances/x)."""
    def path(link: str) -> str:
        return link.split("/projects/", 1)[-1].removeprefix("projects/")

    return bool(a) and bool(b) and path(a) == path(b)


class Names:
    """Every name ccrp gives a GCE resource of one fleet."""

    def __init__(self, fleet: str) -> None:
        self.fleet = fleet
        self.prefix = f"ccrp-{fleet}-"
        self.tag = f"ccrp-{fleet}"  # network tag of the clones: their firewall rules and routes target it
        self.gateway_tag = f"{self.prefix}gateway"  # the entry gateway's (and a builder's beside it)
        self.network = f"{self.prefix}net"
        self.subnetwork = f"{self.prefix}common"

    def instance(self, robot: str, role: str = "clone") -> str:
        return gce_name(f"{self.prefix}{'cri' if role == 'clone' else role}-{robot}")

    def address(self, robot: str, role: str = "clone") -> str:
        """The instance's reserved external address: named as the instance it serves."""
        return self.instance(robot, role)

    def route(self, robot: str) -> str:
        """A clone's route carries its robot's VPN subnet to it; the entry gateway's carries the
        clones' way out to the internet through it."""
        return gce_name(f"{self.prefix}egress" if robot == GATEWAY else f"{self.prefix}vpn-{robot}")

    def firewall(self, purpose: str) -> str:
        return gce_name(f"{self.prefix}{purpose}")

    def describe(self, role: str, robot: str | None = None) -> str:
        """The ownership line of an unlabellable resource."""
        marks = owner_labels(self.fleet, role, robot)
        return " ".join([_DESCRIPTION, *(f"{k}={v}" for k, v in marks.items())])

    def owns_labels(self, labels) -> bool:
        labels = dict(labels or {})
        return labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == self.fleet

    def owns_unlabelled(self, name: str, description: str) -> bool:
        return name.startswith(self.prefix) and self.owns_labels(description_marks(description))

    def label_filter(self, role: str | None = None, robot: str | None = None) -> str:
        """Server-side list filter on the ownership labels (results are re-checked client-side)."""
        marks = {LABEL_MANAGED: "true", LABEL_FLEET: self.fleet}
        if role:
            marks[LABEL_ROLE] = role
        if robot:
            marks[LABEL_ROBOT] = robot
        return " AND ".join(f'(labels.{k} = "{v}")' for k, v in marks.items())


def description_marks(description: str) -> dict[str, str]:
    """The marks of an ownership line; {} for any other description."""
    words = (description or "").split()
    if not words or words[0] != _DESCRIPTION:
        return {}
    return dict(w.split("=", 1) for w in words[1:] if "=" in w)
