"""ccrp's snapshot images on this Docker host: whose state each belongs to, which are orphans, and
the disk they take (`ccrp gc`, `ccrp doctor`).

A snapshot image (`snapshot build`, `snapshot create`) is labelled with the state directory it
belongs to: its absolute path, the random id kept in it (store.STATE_ID_FILE) and this host's name.
An image is an orphan when that directory is gone, or holds another id (deleted and made again):
no state records it any more, so nothing would ever remove it. Images built before these labels
are "unlabelled": nothing says whose they are.

Only images with a tag of the snapshot repositories (`ccrp/<fleet>-clone:*`, snapshots.image_repo)
are considered, and only those tags are removed, without force: an image that also has another
tag (one built FROM a snapshot inherits its labels) keeps it, and Docker refuses to remove an
image a container uses. ccrp's base images (ccrp/base:*, ccrp/robot-sim:*) and the test caches
never match."""

from __future__ import annotations

import json
import os
import re
import socket
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from ...errors import CcrpError
from ...store import read_state_id
from ..base import LABEL_FLEET, LABEL_MANAGED, Finding, ImageOutcome, OwnedResource

LABEL_STATE_DIR = "ccrp-state-dir"
LABEL_STATE_ID = "ccrp-state-id"
LABEL_STATE_HOST = "ccrp-state-host"
# snapshots.image_repo with models/names.py's fleet alphabet.
SNAPSHOT_REPO = re.compile(r"^ccrp/[a-z][a-z0-9]{0,30}-clone:")

THIS, OTHER, ORPHAN, UNLABELLED = "this", "other", "orphan", "unlabelled"


def state_labels(state_dir: Path, state_id: str) -> dict[str, str]:
    # The host's name too: a Docker engine reached from several machines (DOCKER_HOST) holds
    # images whose state directory this one cannot see; those are never judged here.
    return {LABEL_STATE_DIR: str(state_dir.resolve()), LABEL_STATE_ID: state_id, LABEL_STATE_HOST: socket.gethostname()}


@dataclass(frozen=True)
class SnapshotImage:
    id: str  # short (12 hex)
    tags: tuple[str, ...]
    labels: Mapping[str, str]
    size: int  # bytes, its layers and those it shares
    own: int  # bytes of the layers no other image shares: what removing it frees
    containers: tuple[str, ...] = ()  # names of the containers (any state) made from it

    @property
    def snapshot_tags(self) -> tuple[str, ...]:
        return tuple(t for t in self.tags if SNAPSHOT_REPO.match(t))


@dataclass(frozen=True)
class Verdict:
    image: SnapshotImage
    state: str  # this | other | orphan | unlabelled
    detail: str
    # gc may remove it (an unlabelled one only when asked to): no container uses it, no state
    # of this CCRP_HOME records it.
    removable: bool = False


@dataclass
class Census:
    """Every snapshot image of the host, judged for one state directory."""

    verdicts: list[Verdict] = field(default_factory=list)

    def of(self, state: str) -> list[Verdict]:
        return [v for v in self.verdicts if v.state == state]


def listed(client) -> list[SnapshotImage]:
    """The host's images with a snapshot repository tag, from one `docker system df` (sizes with
    and without shared layers, and which containers use each image)."""
    usage = client.df()
    users: dict[str, list[str]] = {}
    for c in usage.get("Containers") or []:
        users.setdefault(c.get("ImageID") or "", []).append(((c.get("Names") or ["?"])[0]).lstrip("/"))
    found = []
    for i in usage.get("Images") or []:
        tags = tuple(t for t in (i.get("RepoTags") or []) if t != "<none>:<none>")
        if not any(SNAPSHOT_REPO.match(t) for t in tags):
            continue
        size, shared = int(i.get("Size") or 0), int(i.get("SharedSize") or 0)
        found.append(SnapshotImage(
            id=i["Id"].removeprefix("sha256:")[:12], tags=tags, labels=i.get("Labels") or {}, size=size,
            own=max(size - max(shared, 0), 0), containers=tuple(sorted(users.get(i["Id"], []))),
        ))
    return sorted(found, key=lambda s: s.tags)


def recorded(home: Path) -> dict[str, str]:
    """Image names and ids any state of this CCRP_HOME records (for new clones, or a clone's
    origin) -> the fleet recording it. What a state records is in use, labels or none."""
    found: dict[str, str] = {}
    for path in sorted(home.glob("*/state.json")):
        try:
            state = json.loads(path.read_text())
            snapshot = state.get("snapshot") or {}
            names = [snapshot.get("image"), snapshot.get("id")] + [
                (r or {}).get("image") for r in (state.get("robots") or {}).values()]
        except (OSError, ValueError, AttributeError):
            continue  # an unreadable state is the fleet's own problem: its commands say so
        for name in names:
            if isinstance(name, str) and name:
                found.setdefault(name, path.parent.name)
    return found


def judge(image: SnapshotImage, fleet: str, state_id: str | None, host: str, records: Mapping[str, str]) -> Verdict:
    """Whose state `image` belongs to, and whether gc may remove it."""
    labels = image.labels
    label_id = labels.get(LABEL_STATE_ID)
    if label_id is None:
        if labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == fleet:
            # This fleet's, from before the labels: its retention and leak rule decide, as before.
            return Verdict(image, THIS, "unlabelled, of this fleet")
        state, detail = UNLABELLED, "no state label (built before ccrp labelled snapshots)"
    elif label_id == state_id:
        return Verdict(image, THIS, "this state")
    else:
        state, detail = _whose(labels, host)
    if state == OTHER:
        return Verdict(image, state, detail)
    user = next((records[k] for k in (image.id, *image.tags) if k in records), None)
    if user is not None:
        return Verdict(image, state, f"{detail}; recorded by fleet {user!r} of this CCRP_HOME")
    if image.containers:
        return Verdict(image, state, f"{detail}; used by container {', '.join(image.containers[:3])}")
    return Verdict(image, state, detail, removable=True)


def _whose(labels: Mapping[str, str], this_host: str) -> tuple[str, str]:
    """ORPHAN or OTHER, with why, for an image labelled with a state that is not this one."""
    directory = labels.get(LABEL_STATE_DIR, "")
    host = labels.get(LABEL_STATE_HOST, "")
    if host != this_host:
        return OTHER, f"state of host {host or '?'}"
    if not os.path.isabs(directory):
        return OTHER, "no state directory in its labels"
    try:
        os.stat(directory)  # not Path.is_dir: a directory this user may not see is not gone
        found = read_state_id(Path(directory))
    except (FileNotFoundError, NotADirectoryError):
        return ORPHAN, f"state directory {directory} is gone"
    except OSError as exc:
        return OTHER, f"state directory {directory} unreadable ({exc.strerror})"
    if found != labels.get(LABEL_STATE_ID):
        return ORPHAN, f"state directory {directory} was made again (another state id)"
    return OTHER, f"state in {directory}"


def census(client, fleet: str, state_id: str | None, home: Path) -> Census:
    host = socket.gethostname()
    records = recorded(home)
    return Census([judge(i, fleet, state_id, host, records) for i in listed(client)])


def remove(client, image: SnapshotImage) -> str:
    """Remove the image's snapshot tags (never force): the image goes with its last tag. What
    happened, in a few words; docker's refusal (a container took it meanwhile) raises CcrpError."""
    from docker.errors import APIError

    for tag in image.snapshot_tags:
        try:
            client.images.remove(tag)
        except APIError as exc:
            raise CcrpError(f"image {tag}: {exc.explanation or exc}") from None
    others = [t for t in image.tags if t not in image.snapshot_tags]
    return f"untagged; kept for its other tags {', '.join(others)}" if others else ""


def megabytes(n: int) -> str:
    return f"{n / 1e6:,.0f} MB"


def sweep(client, fleet: str, state_dir: Path, dry_run: bool, unlabelled: bool = False,
          progress=lambda msg: None) -> list[ImageOutcome]:
    """`ccrp gc` (DockerProvider.sweep_images): the snapshot images on this host whose state
    directory is gone or was made again (orphans), and those from before the labels (unlabelled),
    with what became of each. This state's images are the fleet's leak rule's, a live state's are
    left alone; an image a container uses or a state of this CCRP_HOME records is kept. Unlabelled
    images are removed only when asked (`unlabelled`): nothing says they are not another CCRP_HOME's."""
    found = census(client, fleet, read_state_id(state_dir), state_dir.parent)
    results = []
    for v in found.of(ORPHAN) + found.of(UNLABELLED):
        resource = OwnedResource(kind="image", id=v.image.id, name=", ".join(v.image.snapshot_tags))
        detail = f"{v.detail}; {megabytes(v.image.own)} of its own"
        if not v.removable:
            results.append(ImageOutcome(resource, "kept", detail))
        elif dry_run or (v.state == UNLABELLED and not unlabelled):
            results.append(ImageOutcome(resource, v.state, detail if dry_run else f"{detail}; --unlabelled removes it"))
        else:
            try:
                done = remove(client, v.image)
                progress(f"deleted image {resource.name}")
                results.append(ImageOutcome(resource, "deleted", done or detail))
            except CcrpError as exc:
                results.append(ImageOutcome(resource, "failed", exc.one_line()))
    return results


def finding(client, fleet: str, state_dir: Path) -> Finding:
    """`ccrp doctor` (DockerProvider.images_finding): the disk ccrp's snapshot images take on this
    host, this state's and orphans'."""
    from docker.errors import DockerException

    try:
        found = census(client, fleet, read_state_id(state_dir), state_dir.parent)
    except (DockerException, OSError) as exc:  # a report only: the engine answered doctor's checks before
        return Finding("snapshot images", "warn", f"cannot list them ({type(exc).__name__})")
    parts = []
    for state, what in ((THIS, "this fleet"), (ORPHAN, "orphans"), (UNLABELLED, "unlabelled"), (OTHER, "other states")):
        verdicts = found.of(state)
        if verdicts or state in (THIS, ORPHAN):
            own = sum(v.image.own for v in verdicts)
            parts.append(f"{what} {len(verdicts)} ({megabytes(own)})")
    # Layers shared with other images (the base, each other) are not counted: removing the
    # images frees at least what is shown.
    detail = "; ".join(parts) + " of their own layers"
    waste = [v for v in found.of(ORPHAN) + found.of(UNLABELLED) if v.removable]
    if not waste:
        return Finding("snapshot images", "ok", detail)
    hint = "`ccrp gc --dry-run` lists them, `ccrp gc` removes the orphans"
    if any(v.state == UNLABELLED for v in waste):
        hint += ", `ccrp gc --unlabelled` the unlabelled too"
    return Finding("snapshot images", "warn", detail, hint)
