"""Snapshot images left behind by state directories that are gone: labelled with their state when
built or captured, found and removed by `ccrp gc` (host-wide), counted by `ccrp doctor`. The Docker
engine is faked at the client (`df`, `images.remove`, `images.list`); one test uses the real one."""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import socket
from pathlib import Path
from types import SimpleNamespace

import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.ops.gc import collect_images
from ccrp_cli.models.state import FleetState
from ccrp_cli.providers.docker import snapshot_images as si
from ccrp_cli.store import STATE_ID_FILE, FleetStore, ensure_state_id, read_state_id

SNAPSHOT = {"ccrp-managed": "true", "ccrp-role": "snapshot"}


class FakeImages:
    def __init__(self, engine):
        self.engine = engine

    def remove(self, ref, force=False):
        import docker.errors

        assert not force, "gc never forces a removal"
        if ref in self.engine.conflicts:
            raise docker.errors.APIError("conflict", explanation=f"container is using image {ref}")
        self.engine.removed.append(ref)

    def list(self, filters=None):
        wanted = dict(f.split("=", 1) for f in filters["label"])
        return [SimpleNamespace(id=f"sha256:{i['Id']}", labels=i["Labels"], tags=i["RepoTags"],
                                attrs={"Created": "2026-11-25T00:00:00", "Size": i["Size"]})
                for i in self.engine.images if all(i["Labels"].get(k) == v for k, v in wanted.items())]


class FakeEngine:
    """What docker-py's client answers for `docker system df` and image removals."""

    def __init__(self):
        self.images: list[dict] = []
        self.containers: list[dict] = []
        self.removed: list[str] = []
        self.conflicts: set[str] = set()
        self.images_api = FakeImages(self)

    def add(self, tags, labels=None, size=700_000_000, own=9_000_000, used_by=()):
        image_id = secrets.token_hex(32)
        self.images.append({"Id": image_id, "RepoTags": list(tags), "Labels": dict(labels or {}), "Size": size,
                            "SharedSize": size - own})
        for name in used_by:
            self.containers.append({"Names": [f"/{name}"], "ImageID": f"sha256:{image_id}"})
        return image_id[:12]

    def df(self):
        return {"Images": [{**i, "Id": f"sha256:{i['Id']}"} for i in self.images], "Containers": self.containers}


def client(engine: FakeEngine):
    return SimpleNamespace(df=engine.df, images=engine.images_api)


def state_dir(home: Path, fleet: str) -> tuple[Path, str]:
    root = FleetStore(fleet, home).root
    return root, ensure_state_id(root)


def labelled(fleet: str, directory: Path, state_id: str, host: str | None = None) -> dict:
    labels = SNAPSHOT | {"ccrp-fleet": fleet} | si.state_labels(directory, state_id)
    if host:
        labels[si.LABEL_STATE_HOST] = host
    return labels


def test_the_state_id_is_made_once_and_a_new_directory_gets_another(tmp_path):
    root = tmp_path / "home" / "lab"
    assert read_state_id(root) is None and not root.exists()
    first = ensure_state_id(root)
    assert len(first) == 32 and ensure_state_id(root) == first == read_state_id(root)
    assert (root / STATE_ID_FILE).stat().st_mode & 0o777 == 0o600 and root.stat().st_mode & 0o777 == 0o700
    assert [p.name for p in root.iterdir()] == [STATE_ID_FILE]  # no temp file left
    shutil.rmtree(root)
    assert read_state_id(root) is None and ensure_state_id(root) != first
    (root / STATE_ID_FILE).write_text("")  # emptied by hand: said in one line, never a loop
    with pytest.raises(CcrpError, match="is empty"):
        ensure_state_id(root)


@pytest.fixture
def host(tmp_path, monkeypatch):
    """A Docker host with every kind of image gc must tell apart, and this fleet (lab) in `home`."""
    monkeypatch.setenv("CCRP_HOME", str(tmp_path / "home"))
    home = tmp_path / "home"
    engine = FakeEngine()
    mine, my_id = state_dir(home, "lab")
    live, live_id = state_dir(tmp_path / "elsewhere", "lab")  # same fleet name, another CCRP_HOME
    gone, gone_id = state_dir(tmp_path / "quickstart", "demo")
    shutil.rmtree(tmp_path / "quickstart")
    again, again_old = state_dir(tmp_path / "rerun", "lab")
    shutil.rmtree(again)
    ensure_state_id(again)  # the directory made again: a new id
    FleetStore("other", home).save_state(FleetState(fleet="other", snapshot={"image": "ccrp/other-clone:1"}))
    ids = {
        "mine": engine.add(["ccrp/lab-clone:1"], labelled("lab", mine, my_id)),
        "live": engine.add(["ccrp/lab-clone:2"], labelled("lab", live, live_id)),
        "gone": engine.add(["ccrp/demo-clone:1", "ccrp/demo-clone:nao1-2"], labelled("demo", gone, gone_id)),
        "again": engine.add(["ccrp/lab-clone:3"], labelled("lab", again, again_old)),
        "gone-in-use": engine.add(["ccrp/demo-clone:3"], labelled("demo", gone, gone_id), used_by=["ccrp-demo-cri-nao1"]),
        "gone-derived": engine.add(["ccrp/demo-clone:4", "myorg/app:1"], labelled("demo", gone, gone_id)),
        "derived-only": engine.add(["myorg/app:2"], labelled("demo", gone, gone_id)),  # FROM a snapshot: inherits labels
        "far": engine.add(["ccrp/far-clone:1"], labelled("far", gone, gone_id, host="another-host")),
        "old": engine.add(["ccrp/old-clone:1"], SNAPSHOT | {"ccrp-fleet": "old"}, own=40_000_000),
        "old-in-use": engine.add(["ccrp/old-clone:2"], SNAPSHOT | {"ccrp-fleet": "old"}, used_by=["ccrp-old-cri-nao1"]),
        "old-recorded": engine.add(["ccrp/other-clone:1"], SNAPSHOT | {"ccrp-fleet": "other"}),
        "old-mine": engine.add(["ccrp/lab-clone:0"], SNAPSHOT | {"ccrp-fleet": "lab"}),
        "no-labels": engine.add(["ccrp/bare-clone:1"]),  # snapshot-named, no label at all
    }
    # Never snapshot images, whatever labels they carry.
    for tag in ("ccrp/base:bookworm", "ccrp/base-bare:noetic", "ccrp/robot-sim:noetic", "ccrp-test/snapshot-cache:noetic",
                "ccrp-fake/debian-12-rootfs:latest", "ccrp/lab:1", "ccrp/lab-clone-x:1", "ccrp/Lab-clone:1"):
        engine.add([tag], SNAPSHOT | {"ccrp-fleet": "lab"})
    provider = HostImagesOnly(client=offline_host("lab", engine, mine), fleet="lab")
    return engine, provider, ids


class HostImagesOnly(SimpleNamespace):
    """DockerProvider's Ability.HOST_IMAGES calls, on the fake engine (gc and doctor reach them alone)."""

    from ccrp_cli.providers.docker.provider import DockerProvider

    sweep_images = DockerProvider.sweep_images
    images_finding = DockerProvider.images_finding


def test_gc_lists_orphan_snapshot_images_then_removes_only_those(host):
    engine, provider, ids = host
    dry = {r.resource.id: (r.action, r.detail) for r in collect_images(provider, dry_run=True)}
    assert engine.removed == []
    name = {v: k for k, v in ids.items()}
    assert {name[i]: action for i, (action, _) in dry.items()} == {
        "gone": "orphan", "again": "orphan", "gone-derived": "orphan", "gone-in-use": "kept",
        "old": "unlabelled", "no-labels": "unlabelled", "old-in-use": "kept", "old-recorded": "kept"}
    assert "is gone" in dry[ids["gone"]][1] and "9 MB of its own" in dry[ids["gone"]][1]
    assert "made again" in dry[ids["again"]][1]
    assert "used by container ccrp-demo-cri-nao1" in dry[ids["gone-in-use"]][1]
    assert "recorded by fleet 'other'" in dry[ids["old-recorded"]][1]

    done = {r.resource.id: (r.action, r.detail) for r in collect_images(provider, dry_run=False)}
    assert sorted(engine.removed) == ["ccrp/demo-clone:1", "ccrp/demo-clone:4", "ccrp/demo-clone:nao1-2", "ccrp/lab-clone:3"]
    assert done[ids["gone-derived"]] == ("deleted", "untagged; kept for its other tags myorg/app:1")
    assert done[ids["old"]][0] == "unlabelled" and "--unlabelled removes it" in done[ids["old"]][1]

    engine.removed.clear()
    collect_images(provider, dry_run=False, unlabelled=True)
    assert "ccrp/old-clone:1" in engine.removed and "ccrp/bare-clone:1" in engine.removed
    assert not {"ccrp/old-clone:2", "ccrp/other-clone:1", "ccrp/lab-clone:0", "ccrp/lab-clone:1", "ccrp/lab-clone:2",
                "ccrp/far-clone:1", "ccrp/demo-clone:3"} & set(engine.removed)


def test_a_removal_docker_refuses_is_a_failed_row(host):
    engine, provider, ids = host
    engine.conflicts.add("ccrp/lab-clone:3")  # a container took it between the listing and the removal
    done = {r.resource.id: (r.action, r.detail) for r in collect_images(provider, dry_run=False)}
    assert done[ids["again"]][0] == "failed" and "container is using image" in done[ids["again"]][1]
    assert done[ids["gone"]][0] == "deleted"


@pytest.mark.parametrize("why", ["permission", "name-too-long"])
def test_a_state_directory_that_cannot_be_looked_at_is_not_gone(tmp_path, why):
    """Only "no such file" makes an image's state gone: a directory another user's, or a path this
    machine cannot even look up, keeps its images."""
    if why == "permission" and os.geteuid() == 0:
        pytest.skip("root reads every directory")
    directory = tmp_path / "x" / "lab" if why == "permission" else tmp_path / ("a" * 300) / "lab"
    labels = labelled("lab", tmp_path, "id1") | {si.LABEL_STATE_DIR: str(directory)}
    image = si.SnapshotImage(id="a" * 12, tags=("ccrp/lab-clone:1",), labels=labels, size=1, own=1)
    (tmp_path / "x").mkdir(mode=0o000)
    try:
        verdict = si.judge(image, "other", None, socket.gethostname(), {})
    finally:
        (tmp_path / "x").chmod(0o700)
    assert (verdict.state, verdict.removable) == (si.OTHER, False) and "unreadable" in verdict.detail


def test_doctor_reports_the_disk_of_this_states_images_and_the_orphans(host):
    from ccrp_cli.ops import doctor

    engine, provider, ids = host
    check = doctor._snapshot_images(provider)
    assert check.status == doctor.WARN
    # this fleet: its labelled image and its one from before the labels; orphans: gone, again, gone-in-use, gone-derived
    assert check.detail.startswith("this fleet 2 (18 MB); orphans 4 (36 MB); unlabelled 4 (67 MB); other states 2 (18 MB)")
    assert "ccrp gc --unlabelled" in check.hint
    engine.images = [i for i in engine.images if i["Id"][:12] in (ids["mine"], ids["live"])]
    check = doctor._snapshot_images(provider)
    assert (check.status, check.detail) == (doctor.OK, "this fleet 1 (9 MB); orphans 0 (0 MB); other states 1 (9 MB) of their own layers")


# -- the labels, where images are made ----------------------------------------------------------------

def offline_host(fleet: str, engine, state: Path):
    """DockerHost on the fake engine (no connection made)."""
    from ccrp_cli.providers.docker.client import DockerHost

    host = DockerHost.__new__(DockerHost)
    host.fleet, host.engine, host.state_dir = fleet, client(engine), state
    return host


def _provider(inv, engine):
    from ccrp_cli.providers.docker.provider import DockerProvider

    class Offline(DockerProvider):
        def __init__(self, inv):  # no engine: the client's is the fake
            self.fleet, self.inv, self.client = inv.fleet, inv, offline_host(inv.fleet, engine, FleetStore(inv.fleet).root)

    return Offline(inv)


def test_build_and_create_label_the_image_with_this_state(ccrp_home, monkeypatch):
    from ccrp_cli.ops import snapshots
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.providers.docker import images
    from tests.conftest import LAB

    fleet = Fleet.open(LAB)
    engine = FakeEngine()
    provider = _provider(fleet.inventory, engine)
    built = {}
    monkeypatch.setattr(images, "build_context", lambda *a, **k: {})
    monkeypatch.setattr(images, "build_clone_image", lambda c, tag, text, labels, *a, **k: built.update(tag=tag, labels=labels))
    monkeypatch.setattr(type(provider), "has_image", lambda self, image: True)
    engine.images_api.get = lambda tag: SimpleNamespace(id="sha256:" + "b" * 64, tags=[tag], labels={}, attrs={})
    snapshots.build(fleet, provider, lambda m: None)
    state_id = read_state_id(fleet.store.root)
    assert state_id and built["tag"].startswith("ccrp/lab-clone:")
    assert {k: built["labels"][k] for k in (si.LABEL_STATE_DIR, si.LABEL_STATE_ID, si.LABEL_STATE_HOST, "ccrp-fleet")} == {
        si.LABEL_STATE_DIR: str(fleet.store.root.resolve()), si.LABEL_STATE_ID: state_id,
        si.LABEL_STATE_HOST: socket.gethostname(), "ccrp-fleet": "lab"}

    committed = {}
    container = SimpleNamespace(commit=lambda **kw: committed.update(kw) or SimpleNamespace(
        id="sha256:" + "c" * 64, tags=[f"{kw['repository']}:{kw['tag']}"], labels=kw["conf"]["Labels"], attrs={}))
    monkeypatch.setattr(provider.client, "running_container", lambda robot, role="clone": container)
    provider.create_snapshot("nao1", "ccrp/lab-clone:nao1-1")
    labels = committed["conf"]["Labels"]
    assert (labels["ccrp-robot"], labels["ccrp-role"], labels[si.LABEL_STATE_ID]) == ("nao1", "snapshot", state_id)


def test_this_fleets_snapshots_leave_out_those_of_another_state(ccrp_home, tmp_path):
    from ccrp_cli.fleet import Fleet
    from tests.conftest import LAB

    fleet = Fleet.open(LAB)
    engine = FakeEngine()
    provider = _provider(fleet.inventory, engine)
    mine, my_id = state_dir(ccrp_home, "lab")
    other, other_id = state_dir(tmp_path / "elsewhere", "lab")
    engine.add(["ccrp/lab-clone:1"], labelled("lab", mine, my_id))
    engine.add(["ccrp/lab-clone:2"], labelled("lab", other, other_id))  # retention here must not remove it
    engine.add(["ccrp/lab-clone:0"], SNAPSHOT | {"ccrp-fleet": "lab"})  # from before the labels: the fleet's, as before
    assert sorted(s.name for s in provider.list_snapshots()) == ["ccrp/lab-clone:0", "ccrp/lab-clone:1"]


# -- the real engine ------------------------------------------------------------------------------

BASE = "ccrp/base:bookworm"
INVENTORY = """\
fleet: {fleet}
provider: {{kind: docker, public_cidr: 172.31.250.0/24}}
common: {{cidr: 10.251.0.0/24}}
robots:
  - name: nao1
"""


@pytest.fixture
def engine():
    docker = pytest.importorskip("docker")
    try:
        real = docker.from_env(timeout=120)
        real.images.get(BASE)
    except docker.errors.DockerException as exc:
        pytest.skip(f"needs a Docker engine with {BASE} ({type(exc).__name__})")
    yield real
    real.close()


def test_gc_on_docker_removes_the_image_of_a_deleted_state_directory(engine, tmp_path, monkeypatch):
    """A tiny labelled image, as `snapshot build` labels it, from a CCRP_HOME that is then
    deleted: `gc --dry-run` lists it and removes nothing, `gc` removes it; the image of a state
    that still lives stays. Everything made here is removed, whatever happens."""
    import docker

    from ccrp_cli.fleet import Fleet
    from ccrp_cli.providers import get_provider
    from ccrp_cli.providers.docker import images
    from tests.conftest import run_ccrp

    fleet = f"hgc{secrets.token_hex(4)}"
    inventory = tmp_path / "ccrp.yaml"
    inventory.write_text(INVENTORY.format(fleet=fleet))
    tags = {"quick": f"ccrp/{fleet}-clone:quick", "live": f"ccrp/{fleet}-clone:live"}
    try:
        for which, home in (("quick", tmp_path / "quickstart"), ("live", tmp_path / "live")):
            monkeypatch.setenv("CCRP_HOME", str(home))
            provider = get_provider(Fleet.open(inventory).inventory)
            images.build_clone_image(engine, tags[which], f"FROM {BASE}\n", provider.snapshot_labels())
            provider.close()
        shutil.rmtree(tmp_path / "quickstart")
        FleetStore(fleet, tmp_path / "live").save_state(FleetState(fleet=fleet))  # gc deletes only with a state

        dry = json.loads(run_ccrp("gc", "-i", str(inventory), "--dry-run", "--json", home=tmp_path / "live", check=True).stdout)
        rows = {r["name"]: r for r in dry if r["kind"] == "image"}
        assert rows[tags["quick"]]["action"] == "orphan" and tags["live"] not in rows, dry
        engine.images.get(tags["quick"])  # the dry run removed nothing
        others = [name for name, r in rows.items() if r["action"] == "orphan" and name != tags["quick"]]
        if others:  # another run's orphans: not this test's to remove
            pytest.skip(f"this host has orphan snapshot images this test did not make: {others}")

        done = json.loads(run_ccrp("gc", "-i", str(inventory), "--json", home=tmp_path / "live", check=True).stdout)
        assert [r["name"] for r in done if r["action"] == "deleted"] == [tags["quick"]], done
        with pytest.raises(docker.errors.ImageNotFound):
            engine.images.get(tags["quick"])
        engine.images.get(tags["live"])
        engine.images.get(BASE)
    finally:
        for tag in tags.values():
            with contextlib.suppress(docker.errors.ImageNotFound):  # gc removed it, or it was never built
                engine.images.remove(tag)
