"""ccrp deploy (docs/workloads.md, Deploy): the workspace and nodes onto running clones. The clones
here are directories: pushed files land under them and deploy's scripts run for real, with the
clone's paths moved under the directory and a stand-in systemctl; the build is replaced by a tar."""

from __future__ import annotations

import io
import json
import re
import subprocess
import shutil
import tarfile
import threading
import time
from pathlib import Path

import pytest
import yaml

from ccrp_cli.ops import deploy, install_space
from ccrp_cli.services import workloads
from ccrp_cli.errors import CcrpError, InputError
from ccrp_cli.fleet import Fleet
from ccrp_cli.providers.base import CloneRecord, CloneState
from ccrp_cli.services.workloads import INDEX, node_files, packages_record, snapshot_software
from tests.conftest import LAB
from tests.inprocess_cli import run_ccrp_inprocess

CATKIN_XML = """<?xml version="1.0"?>
<package format="2"><name>mapper</name><version>1.0.0</version><description>x</description>
<maintainer email="a@b.c">a</maintainer><license>MIT</license><buildtool_depend>catkin</buildtool_depend></package>
"""
MOVED = re.compile(r"(/etc/systemd/system|/etc/ccrp|/opt/ccrp|/var/lib/ccrp|/etc/openvpn)")
MAPPER = "/etc/systemd/system/ccrp-run-mapper.service"


def install_tar(text: str) -> bytes:
    """An install space as deploy reads it out of the image: the directory `workspace/`."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data in (("workspace", None), ("workspace/setup.sh", text.encode())):
            info = tarfile.TarInfo(name)
            if data is None:
                info.type, info.mode = tarfile.DIRTYPE, 0o755
                tar.addfile(info)
            else:
                info.size, info.mode = len(data), 0o644
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


class Clones:
    """A fake provider whose clones are directories (root/<robot>), recording pushes and execs."""

    kind = "docker"
    max_parallel = 4

    def __init__(self, root: Path, robots: list[str]) -> None:
        self.root, self.robots = root, robots
        self.pushes: list[tuple[str, str, int]] = []
        self.execs: list[tuple[str, list[str]]] = []
        self.states: dict[str, tuple[str, str, int]] = {}  # unit -> (ActiveState, SubState, NRestarts)
        self.bin = root / "bin"
        self.bin.mkdir(parents=True)
        (self.bin / "systemctl").write_text('#!/bin/sh\necho "$@" >> "$CALLS"\n')
        (self.bin / "systemctl").chmod(0o755)

    def at(self, robot: str, path: str) -> Path:
        return self.root / robot / path.lstrip("/")

    def calls(self, robot: str) -> list[str]:
        log = self.root / robot / "calls"
        return log.read_text().splitlines() if log.exists() else []

    def query(self) -> dict[str, CloneRecord]:
        return {r: CloneRecord(robot=r, provider_id=f"id-{r}", state=CloneState.RUNNING, status="running")
                for r in self.robots}

    transport = property(lambda self: self)  # a fake clone is its own transport
    def push_files(self, robot: str, files: list, restart=()) -> None:
        for f in files:
            self.pushes.append((robot, f.dest, f.mode))
            path = self.at(robot, f.dest)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(f.content)
            path.chmod(f.mode)

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        self.execs.append((robot, argv))
        if argv[:2] == ["systemctl", "show"]:
            blocks = []
            for unit in argv[4:]:
                active, sub, restarts = self.states.get(unit, ("active", "running", 0))
                blocks.append(f"Id={unit}\nActiveState={active}\nSubState={sub}\nNRestarts={restarts}\n")
            return 0, "\n".join(blocks)
        if argv[0] == "journalctl":
            return 0, "\n".join(json.dumps({"__CURSOR": str(i), "_SYSTEMD_UNIT": argv[-3], "MESSAGE": f"line {i}"})
                                for i in range(8))
        base = str(self.root / robot)
        moved = [MOVED.sub(lambda m: base + m.group(1), word) for word in argv]
        proc = subprocess.run(moved, capture_output=True, text=True, check=False,
                              env={"PATH": f"{self.bin}:/usr/bin:/bin", "CALLS": f"{base}/calls"})
        return proc.returncode, (proc.stdout + proc.stderr).replace(base, "")  # paths as the clone has them

    def scripts(self, robot: str | None = None) -> list[str]:
        """The deploy actions run, in order."""
        return [argv[4] for r, argv in self.execs if argv[:2] == ["sh", "-c"] and argv[3] == "ccrp-deploy"
                and (robot is None or r == robot)]


def write_inventory(tmp_path: Path, **software) -> Path:
    data = yaml.safe_load(LAB.read_text())
    data.pop("services", None)
    for robot in data["robots"]:
        robot.pop("services", None)
    data["software"] = {"workspace": "ws", "run": [{"name": "mapper", "command": ["mapper"]}], **software}
    path = tmp_path / "inventory.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


@pytest.fixture
def fleet(tmp_path, ccrp_home):
    """The lab fleet with a catkin workspace, its clones made from its snapshot (units, index and
    install space in place), each clone a directory of `Clones`."""
    pkg = tmp_path / "ws" / "src" / "mapper"
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text(CATKIN_XML)
    (pkg / "main.cpp").write_text("int main(){}")
    path = write_inventory(tmp_path)
    fleet = Fleet.open(path)
    sw = snapshot_software(fleet.inventory, path)
    state = fleet.load_allocated()
    state.snapshot = {"image": "ccrp/lab-clone:1", "id": "abc", "software": sw.digest, "packages": packages_record(sw)}
    names = [r.name for r in fleet.members(state)]
    clones = Clones(tmp_path / "clones", names)
    for name in names:
        rec = state.robots[name]
        rec.phase, rec.provider_id, rec.image = "ready", f"id-{name}", "abc"
        rec.software, rec.packages = sw.digest, packages_record(sw)
        clones.push_files(name, node_files(fleet.inventory, fleet.robot(state, name), sw.digest))
        clones.at(name, "/opt/ccrp/workspace").mkdir(parents=True)
        clones.at(name, "/opt/ccrp/workspace/setup.sh").write_text("v1")
    fleet.store.save_state(state)
    clones.pushes.clear()
    return fleet, clones, sw.digest


def change_workspace(fleet: Fleet) -> str:
    (fleet.path.parent / "ws" / "src" / "mapper" / "main.cpp").write_text("int main(){return 1;}")
    fleet = Fleet.open(fleet.path)
    return snapshot_software(fleet.inventory, fleet.path).digest


@pytest.fixture
def built(monkeypatch):
    """deploy's build, replaced by an install space whose setup.sh says v2; records its calls."""
    calls = []

    def build(fleet, software, progress, provider=None, on=None):
        assert on is None  # this host's engine builds (it answers, below)
        calls.append(software.digest)
        return install_tar("v2")

    import ccrp_cli.providers as providers

    monkeypatch.setattr(providers, "local_engine_answers", lambda: True)
    monkeypatch.setattr(deploy, "build_install_space", build)
    monkeypatch.setattr(workloads, "HEALTH_SECONDS", 0.2)
    monkeypatch.setattr(workloads, "HEALTH_INTERVAL", 0.05)
    return calls


def test_a_changed_workspace_reaches_the_clones_and_restarts_their_nodes(fleet, built):
    fleet, clones, old = fleet
    new = change_workspace(fleet)
    results = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, type_="nao")
    assert [(r.robot, r.action) for r in results] == [("nao1", "deployed"), ("nao2", "deployed")], results
    assert built == [new]  # one build for every clone
    assert f"workspace {old} -> {new}" in results[0].detail and "restart mapper" in results[0].detail
    # The clones had setup.sh (v1): sent as a delta over it, named in the result.
    assert results[0].sent_bytes and f"; sent {results[0].sent_bytes / 1e3:.1f} kB" in results[0].detail
    stages = [argv[5:] for r, argv in clones.execs if argv[:2] == ["sh", "-c"] and argv[4] == "stage"]
    assert stages == [[new, "delta"], [new, "delta"]], stages
    for robot in ("nao1", "nao2"):
        assert clones.at(robot, "/opt/ccrp/workspace/setup.sh").read_text() == "v2"
        for gone in ("/opt/ccrp/workspace.prev", "/opt/ccrp/workspace.new", f"/var/lib/ccrp/deploy/{new}.tar.b64",
                     "/var/lib/ccrp/deploy/prev"):
            assert not clones.at(robot, gone).exists(), gone
        assert clones.at(robot, "/var/lib/ccrp/deploy/current").read_text().strip() == new
        assert json.loads(clones.at(robot, INDEX).read_text())["software"] == new
        assert "restart ccrp-run-mapper.service" in clones.calls(robot)
        assert clones.scripts(robot) == ["probe", "stage", "swap", "commit"]
        # The tar went as a root-only file of deploy's own directory.
        assert (robot, f"/var/lib/ccrp/deploy/{new}.tar.b64", 0o600) in clones.pushes
    assert clones.scripts("turtlebot1") == []  # not of the type
    state = Fleet.open(fleet.path).store.load_state()
    assert state.robots["nao1"].software == new and state.robots["turtlebot1"].software == old
    # Again: nothing to do, nothing built or pushed.
    clones.pushes.clear()
    again = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert [(r.robot, r.action) for r in again] == [("nao1", "current")] and built == [new] and clones.pushes == []


def test_a_changed_run_list_restarts_only_that_node_without_a_build(fleet, built, tmp_path):
    fleet, clones, _ = fleet
    write_inventory(tmp_path, run=[{"name": "mapper", "command": ["mapper", "--fast"]}, {"name": "faces", "command": ["faces"]}])
    [result] = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao2")
    assert result.action == "deployed" and "start faces" in result.detail and "restart mapper" in result.detail, result
    assert built == [] and clones.scripts("nao2") == ["probe", "stage", "begin", "commit"]  # no workspace swapped
    assert clones.at("nao2", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert "--fast" in clones.at("nao2", MAPPER).read_text()


def test_a_node_that_does_not_stay_up_puts_the_clone_back(fleet, built):
    fleet, clones, old = fleet
    unit_before = clones.at("nao1", MAPPER).read_text()
    index_before = clones.at("nao1", INDEX).read_text()
    change_workspace(fleet)
    clones.states["ccrp-run-mapper.service"] = ("activating", "auto-restart", 2)
    from ccrp_cli.cli import output

    [result] = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert result.action == "failed", result
    assert "ccrp-run-mapper.service is activating/auto-restart" in result.detail and "rolled back" in result.detail
    assert "line 7" in result.detail and "line 2" not in result.detail  # its last 5 journal lines
    # The previous workspace, units and index, and the node restarted on them.
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert clones.at("nao1", MAPPER).read_text() == unit_before
    assert clones.at("nao1", INDEX).read_text() == index_before
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/current").exists()
    assert not clones.at("nao1", "/opt/ccrp/workspace.prev").exists()
    assert clones.scripts("nao1") == ["probe", "stage", "swap", "rollback"]
    calls = clones.calls("nao1")
    assert calls.count("restart ccrp-run-mapper.service") == 2  # the new version, then the previous one
    assert Fleet.open(fleet.path).store.load_state().robots["nao1"].software == old
    assert output.results([result], as_json=True) == 1


def test_a_node_restarted_by_systemd_during_the_check_fails_it(fleet, built):
    fleet, clones, _ = fleet
    change_workspace(fleet)
    seen = []

    def flapping(robot, argv, timeout=60, real=clones.exec):
        if argv[:2] == ["systemctl", "show"]:
            seen.append(1)
            clones.states["ccrp-run-mapper.service"] = ("active", "running", len(seen))
        return real(robot, argv, timeout)

    clones.exec = flapping
    [result] = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert result.action == "failed" and "restarted 1 time(s)" in result.detail, result


def test_an_apt_or_pip_change_is_refused_before_anything(fleet, built, tmp_path):
    fleet, clones, _ = fleet
    write_inventory(tmp_path, apt=["htop"])
    with pytest.raises(InputError) as refused:
        deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None)
    line = refused.value.one_line()
    assert "apt + htop" in line and "build a new snapshot and re-create the clones" in line and "\n" not in line
    assert clones.execs == [] and built == []


def test_dry_run_says_what_would_change_and_changes_nothing(fleet, built, tmp_path):
    fleet, clones, old = fleet
    new = change_workspace(fleet)
    before = {r: clones.at(r, MAPPER).read_text() for r in clones.robots}
    results = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, dry_run=True)
    assert {r.action for r in results} == {"would deploy"}
    assert results[0].detail == f"workspace {old} -> {new}; restart mapper", results[0]
    assert built == [] and clones.pushes == [] and set(clones.scripts()) == {"probe"}
    assert {r: clones.at(r, MAPPER).read_text() for r in clones.robots} == before
    assert all(clones.calls(r) == [] for r in clones.robots)
    assert Fleet.open(fleet.path).store.load_state().robots["nao1"].software == old


def test_a_secret_reaches_its_node_by_name_only_and_a_changed_one_restarts_it(fleet, built, tmp_path, ccrp_home):
    """A node's secret: pushed root-only, named (never shown) in dry-run and results, its node
    restarted when it changes, deleted when dropped; its value in no line, result or state."""
    fleet, clones, _ = fleet
    value = "tok-6f1d2c9a"
    (tmp_path / "token").write_text(value)
    node = {"name": "mapper", "command": ["mapper"], "env": {"MODE": "fast"}, "secrets": {"API_TOKEN": "token"}}
    write_inventory(tmp_path, run=[node])
    secret = "/etc/openvpn/server/ccrp/keys/nodes/mapper/API_TOKEN"
    lines: list[str] = []
    [dry] = deploy.deploy(Fleet.open(fleet.path), clones, lines.append, robot="nao1", dry_run=True)
    assert dry.action == "would deploy" and dry.detail.endswith("restart mapper; secret mapper/API_TOKEN changed"), dry
    [result] = deploy.deploy(Fleet.open(fleet.path), clones, lines.append, robot="nao1")
    assert result.action == "deployed" and "secret mapper/API_TOKEN changed" in result.detail, result
    assert clones.at("nao1", secret).read_text() == value and ("nao1", secret, 0o600) in clones.pushes
    unit = clones.at("nao1", MAPPER).read_text()
    assert f"LoadCredential=API_TOKEN:{secret}" in unit and 'Environment="MODE=fast"' in unit
    (tmp_path / "token").write_text(value + "-rotated")
    calls = len(clones.calls("nao1"))
    [rotated] = deploy.deploy(Fleet.open(fleet.path), clones, lines.append, robot="nao1")
    assert rotated.detail.endswith("restart mapper; secret mapper/API_TOKEN changed"), rotated
    assert "restart ccrp-run-mapper.service" in clones.calls("nao1")[calls:]
    assert clones.at("nao1", secret).read_text() == value + "-rotated"
    [again] = deploy.deploy(Fleet.open(fleet.path), clones, lines.append, robot="nao1")
    assert again.action == "current", again
    write_inventory(tmp_path, run=[{k: v for k, v in node.items() if k != "secrets"}])
    [dropped] = deploy.deploy(Fleet.open(fleet.path), clones, lines.append, robot="nao1")
    assert dropped.action == "deployed" and not clones.at("nao1", secret).exists(), dropped
    kept = [p for p in ccrp_home.rglob("*") if p.is_file()]
    assert "state.json" in {p.name for p in kept}
    shown = [*lines, *(r.detail for r in (dry, result, rotated, again, dropped)), *(p.read_text(errors="replace") for p in kept)]
    assert lines and not [text for text in shown if value in text]


def swapped_clone(tmp_path, systemctl: str | None = None) -> Clones:
    """A clone r that ran workspace v1 and unit ccrp-run-a, then staged and swapped in v2 (DEPLOY_SH
    alone); `systemctl`: the script its systemctl is instead of the recording one."""
    clones = Clones(tmp_path, ["r"])
    if systemctl is not None:
        (clones.bin / "systemctl").write_text(systemctl)
    clones.at("r", "/opt/ccrp/workspace").mkdir(parents=True)
    clones.at("r", "/opt/ccrp/workspace/setup.sh").write_text("v1")
    clones.at("r", "/etc/systemd/system").mkdir(parents=True)
    clones.at("r", "/etc/systemd/system/ccrp-run-a.service").write_text("old a")
    clones.exec("r", ["mkdir", "-p", "-m", "0700", install_space.DEPLOY_DIR])
    clones.at("r", f"{install_space.DEPLOY_DIR}/d2.tar.b64").write_text(install_space.pushed(install_tar("v2")))
    for action in (["stage", "d2"], ["swap", "d2"]):
        install_space.script(clones, "r", *action)
    return clones


def test_the_install_space_swap_and_rollback_for_real(tmp_path):
    """DEPLOY_SH alone: stage and swap keep the previous workspace, rollback brings it back and
    removes a unit the failed version added."""
    clones = swapped_clone(tmp_path)
    assert clones.at("r", "/opt/ccrp/workspace/setup.sh").read_text() == "v2"
    assert clones.at("r", "/opt/ccrp/workspace.prev/setup.sh").read_text() == "v1"
    clones.at("r", "/etc/systemd/system/ccrp-run-a.service").write_text("new a")
    clones.at("r", "/etc/systemd/system/ccrp-run-b.service").write_text("new b")
    install_space.script(clones, "r", "rollback", "a", "b")
    assert clones.at("r", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert clones.at("r", "/etc/systemd/system/ccrp-run-a.service").read_text() == "old a"
    assert not clones.at("r", "/etc/systemd/system/ccrp-run-b.service").exists()
    calls = clones.calls("r")
    assert "disable --now ccrp-run-b.service" in calls and "restart ccrp-run-a.service" in calls
    assert "restart ccrp-run-b.service" not in calls
    assert not clones.at("r", "/opt/ccrp/workspace.prev").exists()


def test_a_rollback_whose_enable_fails_still_starts_the_previous_nodes(tmp_path):
    """Issue 39: DEPLOY_SH's rollback runs every step whatever failed before it (it stopped at a
    failed `systemctl enable` under `set -e`, before the previous nodes started) and names what
    failed."""
    clones = swapped_clone(tmp_path, systemctl='#!/bin/sh\necho "$@" >> "$CALLS"\n[ "$1" != enable ]\n')
    assert clones.at("r", "/var/lib/ccrp/deploy/pending").read_text() == "swapped\n"
    clones.at("r", "/etc/systemd/system/ccrp-run-a.service").write_text("new a")
    with pytest.raises(deploy.CcrpError) as failed:
        install_space.script(clones, "r", "rollback", "a")
    assert "steps that failed: systemctl enable ccrp-run-a.service" in failed.value.message, failed.value.message
    calls = clones.calls("r")
    assert calls[-3:] == ["enable ccrp-run-a.service", "restart ccrp-run-a.service", "start ccrp-run-a.service"], calls
    assert clones.at("r", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert clones.at("r", "/etc/systemd/system/ccrp-run-a.service").read_text() == "old a"
    assert not clones.at("r", "/var/lib/ccrp/deploy/pending").exists()
    assert not clones.at("r", "/var/lib/ccrp/deploy/current").exists()  # the clone had none before


def test_ctrl_c_starts_no_further_clone_and_puts_the_one_mid_swap_back(fleet, built, monkeypatch):
    """Issue 39: Ctrl-C reaches the main thread only. The clone being changed (nao1, in its health
    check) goes back as it was; those queued behind it (one at a time here) are not started; each
    robot's line says which; then the interruption goes on (exit 130 in the CLI)."""
    import _thread

    fleet, clones, old = fleet
    change_workspace(fleet)
    clones.max_parallel = 1
    monkeypatch.setattr(workloads, "HEALTH_SECONDS", 30.0)  # the interruption, not the window, ends the check
    real = clones.exec

    def ctrl_c(robot, argv, timeout=60):
        if argv[:2] == ["systemctl", "show"] and not said_ctrl_c:
            said_ctrl_c.append(robot)
            _thread.interrupt_main()  # as SIGINT: KeyboardInterrupt in the main thread
        return real(robot, argv, timeout)

    said_ctrl_c: list[str] = []
    clones.exec = ctrl_c
    said: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        deploy.deploy(Fleet.open(fleet.path), clones, said.append)
    assert said_ctrl_c == ["nao1"]
    assert clones.scripts("nao1") == ["probe", "stage", "swap", "rollback"]
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/pending").exists()
    for robot in ("nao2", "turtlebot1"):  # queued: probed, never changed
        assert clones.scripts(robot) == ["probe"] and clones.calls(robot) == [], robot
        assert clones.at(robot, "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert "[nao1] interrupted: rolled back: the previous version runs" in said, said
    assert "[nao2] not started: interrupted" in said and "[turtlebot1] not started: interrupted" in said, said
    state = Fleet.open(fleet.path).store.load_state()
    assert {rec.software for rec in state.robots.values()} == {old}


def killed_after_the_swap(fleet: Fleet, clones: Clones, robot: str) -> str:
    """What a deploy killed between the swap and its health check leaves on robot's clone (its
    steps run here as apply runs them, then nothing): the new workspace and units, unchecked."""
    fleet = Fleet.open(fleet.path)
    state = fleet.store.load_state()
    change = deploy.probe(workloads.DeployInputs.read(fleet, state, [robot]), clones, state, robot)
    tar = install_space.pushed(install_tar("v2"))
    clones.exec(robot, ["mkdir", "-p", "-m", "0700", install_space.DEPLOY_DIR])
    clones.at(robot, f"{install_space.DEPLOY_DIR}/{change.new}.tar.b64").write_text(tar)
    install_space.script(clones, robot, "stage", change.new)
    install_space.script(clones, robot, "swap", change.new)
    workloads.apply_nodes(clones, robot, change.files, change.have)
    clones.execs.clear()
    return change.new


def test_a_deploy_killed_before_its_check_is_checked_by_the_next(fleet, built):
    """Issue 39: the clone keeps a pending mark from the swap to the commit; the next deploy does
    not take the clone as current, it makes the check and commits."""
    fleet, clones, old = fleet
    new = change_workspace(fleet)
    assert killed_after_the_swap(fleet, clones, "nao1") == new
    assert clones.at("nao1", "/var/lib/ccrp/deploy/pending").exists()
    dry = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1", dry_run=True)
    assert [(r.action, r.detail) for r in dry] == [("would deploy", "a deploy stopped before its check: check its nodes (mapper)")]
    [result] = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert result.action == "deployed" and "finished" in result.detail and new in result.detail, result
    assert clones.scripts("nao1") == ["probe", "probe", "commit"]  # the dry run's probe, then this one's
    assert any(argv[:2] == ["systemctl", "show"] for _, argv in clones.execs)
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/pending").exists()
    assert not clones.at("nao1", "/opt/ccrp/workspace.prev").exists()
    assert Fleet.open(fleet.path).store.load_state().robots["nao1"].software == new != old
    again = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert [r.action for r in again] == ["current"] and built == []


def test_a_deploy_killed_before_its_check_whose_node_fails_goes_back(fleet, built):
    fleet, clones, old = fleet
    change_workspace(fleet)
    killed_after_the_swap(fleet, clones, "nao1")
    clones.states["ccrp-run-mapper.service"] = ("activating", "auto-restart", 1)
    [result] = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert result.action == "failed", result
    assert "ccrp-run-mapper.service is activating/auto-restart after a deploy stopped before its check" in result.detail
    assert "rolled back" in result.detail and "line 7" in result.detail
    assert clones.scripts("nao1") == ["probe", "rollback"]
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/pending").exists()
    assert Fleet.open(fleet.path).store.load_state().robots["nao1"].software == old


def test_a_deploy_killed_before_its_check_then_other_software_goes_back_first(fleet, built, tmp_path):
    """The inventory changed since the killed deploy: what it left (never checked, not wanted) goes
    back to the version before it, then the inventory's software is deployed as on any clone."""
    fleet, clones, _ = fleet
    change_workspace(fleet)
    killed_after_the_swap(fleet, clones, "nao1")
    write_inventory(tmp_path, run=[{"name": "mapper", "command": ["mapper", "--fast"]}])
    said: list[str] = []
    [result] = deploy.deploy(Fleet.open(fleet.path), clones, said.append, robot="nao1")
    assert result.action == "deployed" and result.detail.startswith("a deploy stopped before its check rolled back; "), result
    assert clones.scripts("nao1") == ["probe", "rollback", "probe", "stage", "swap", "commit"]
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v2"
    assert "--fast" in clones.at("nao1", MAPPER).read_text()
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/pending").exists()


def test_bad_targets_are_one_line(fleet, built, tmp_path):
    fleet, clones, _ = fleet
    for kwargs, words in (({"robot": "ghost"}, "not in fleet"), ({"type_": "drone"}, "has type"),
                          ({"robot": "nao1", "type_": "nao"}, "not both")):
        with pytest.raises(InputError, match=words):
            deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, **kwargs)
    assert clones.execs == []
    for args in (["--robot", "ghost"], ["--type", "drone"]):
        code, _, err = run_ccrp_inprocess("deploy", "-i", str(fleet.path), *args, home=tmp_path / "home")
        assert code == 2 and len(err.splitlines()) == 1 and err.startswith("ccrp: error: "), (args, err)


def test_a_clone_from_before_deploy_without_a_record_is_refused(fleet, built):
    fleet, clones, _ = fleet
    change_workspace(fleet)
    state = fleet.store.load_state()
    state.snapshot.pop("packages")
    state.robots["nao1"].packages = None
    fleet.store.save_state(state)
    with pytest.raises(InputError, match="does not record"):
        deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")


def test_snapshot_packages_digest_is_what_deploy_compares(fleet):
    fleet, _, digest = fleet
    sw = snapshot_software(fleet.inventory, fleet.path)
    record = json.loads(packages_record(sw))
    assert record == {"distro": "noetic", "apt": sw.apt, "pip": sw.pip} and sw.digest == digest
    assert fleet.store.load_state().snapshot["packages"] == packages_record(sw)


@pytest.mark.parametrize("inventory", ["lab.yaml", "aws.yaml"])
def test_the_workspace_is_built_on_this_hosts_engine_whatever_the_backend(inventory, monkeypatch):
    """providers.build_workspace (docker/workspace.py), the engine faked: a Docker fleet's own base
    image, Docker's default else; the install space read out of a container never started; the
    older deploy images of the fleet dropped; the client closed."""
    from types import SimpleNamespace

    from ccrp_cli.loader import load_inventory
    from ccrp_cli.providers import build_workspace
    from ccrp_cli.providers.docker import images, workspace

    inv = load_inventory(LAB.parent / inventory)
    done: list = []

    class Container:
        def get_archive(self, path):
            done.append(("read", path))
            return iter([b"tar", b"!"]), {}

        def remove(self, force):
            done.append(("removed", force))

    class Images:
        def list(self, filters):
            done.append(("list", tuple(filters["label"])))
            return [SimpleNamespace(id="old", tags=[f"ccrp/{inv.fleet}-deploy:0ld"]),
                    SimpleNamespace(id="new", tags=[f"ccrp/{inv.fleet}-deploy:d1g"])]

        def remove(self, image_id, force):
            done.append(("drop", image_id, force))

    client = SimpleNamespace(containers=SimpleNamespace(create=lambda tag, labels: done.append(("create", tag)) or Container()),
                             images=Images(), close=lambda: done.append(("closed",)))
    monkeypatch.setattr(workspace, "local_engine", lambda: client)
    monkeypatch.setattr(images, "ensure_base", lambda c, base, plat, progress: done.append(("base", base)))
    monkeypatch.setattr(images, "dockerfile", lambda fleet, distro, base, plat, software, agents: f"FROM {base} {agents}")
    monkeypatch.setattr(images, "build_context", lambda plat, progress, distro, software, agents: dict.fromkeys(agents))
    monkeypatch.setattr(images, "build_clone_image", lambda c, tag, text, labels, progress, files, what:
                        done.append(("build", tag, text, labels["ccrp-role"], list(files), what)))
    data = build_workspace(inv, SimpleNamespace(digest="d1g"), ("relay", "api_manager"), lambda m: None)
    tag = f"ccrp/{inv.fleet}-deploy:d1g"
    base = inv.provider.base_image if inventory == "lab.yaml" else images.DEFAULT_BASE
    assert data == b"tar!"
    # The snapshot's own Dockerfile and context, its agents too (the core's, as snapshot build's).
    assert done == [("base", base), ("build", tag, f"FROM {base} ('relay', 'api_manager')", "deploy",
                     ["relay", "api_manager"], "deploy build"), ("create", tag),
                    ("read", "/opt/ccrp/workspace"), ("removed", True),
                    ("list", (f"ccrp-fleet={inv.fleet}", "ccrp-role=deploy")), ("drop", "old", False), ("closed",)]


class PerRobotStates(Clones):
    """Clones whose node state may differ per robot: (robot, unit) -> state, then the unit's."""

    def __init__(self, root: Path, robots: list[str]) -> None:
        super().__init__(root, robots)
        self.robot_states: dict[tuple[str, str], tuple[str, str, int]] = {}
        self.busy, self.most = 0, 0
        self.lock = threading.Lock()

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        if argv[:2] == ["systemctl", "show"]:
            with self.lock:
                self.busy += 1
                self.most = max(self.most, self.busy)
            try:
                time.sleep(0.05)  # clones changed at once overlap here
                blocks = [f"Id={u}\nActiveState={a}\nSubState={s}\nNRestarts={n}\n"
                          for u in argv[4:] for a, s, n in [self.robot_states.get((robot, u), ("active", "running", 0))]]
                return 0, "\n".join(blocks)
            finally:
                with self.lock:
                    self.busy -= 1
        return super().exec(robot, argv, timeout)


@pytest.fixture
def per_robot(fleet, tmp_path):
    fleet, clones, old = fleet
    mine = PerRobotStates(tmp_path / "clones2", clones.robots)
    shutil.rmtree(mine.root)
    shutil.copytree(clones.root, mine.root, symlinks=True)
    return fleet, mine, old


def test_a_failing_canary_changes_no_other_clone(per_robot, built):
    fleet, clones, old = per_robot
    new = change_workspace(fleet)
    clones.robot_states[("nao1", "ccrp-run-mapper.service")] = ("activating", "auto-restart", 2)
    results = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, canary=1)
    by = {r.robot: r for r in results}
    assert by["nao1"].action == "failed" and "rolled back" in by["nao1"].detail, by["nao1"]
    others = [r for r in results if r.robot != "nao1"]
    assert others and all(r.action == "not started" and "canary nao1 did not deploy" in r.detail for r in others)
    for r in others:  # probed, nothing more: no stage, no swap, the old workspace
        assert clones.scripts(r.robot) == ["probe"] and clones.at(r.robot, "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    state = Fleet.open(fleet.path).store.load_state()
    assert {r.robot: state.robots[r.robot].software for r in results} == {r.robot: old for r in results}
    from ccrp_cli.cli import output

    assert output.results(results, as_json=True) == 1  # nothing deployed
    # Fixed: the canary goes first again, then the others, at most 2 at once.
    clones.robot_states.clear()
    results = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, canary=1, max_parallel=2)
    assert {r.action for r in results} == {"deployed"} and clones.most <= 2, (results, clones.most)
    assert Fleet.open(fleet.path).store.load_state().robots["turtlebot1"].software == new


def test_the_canaries_are_clones_with_something_to_change(per_robot, built):
    fleet, clones, _ = per_robot
    change_workspace(fleet)
    [first] = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert first.action == "deployed"
    clones.robot_states[("nao2", "ccrp-run-mapper.service")] = ("failed", "failed", 0)
    results = {r.robot: r for r in deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, canary=1)}
    # nao1 was current already: nao2 is the canary, fails, and no one else is changed.
    assert results["nao1"].action == "current" and results["nao2"].action == "failed"
    assert all(r.action == "not started" for n, r in results.items() if n not in ("nao1", "nao2"))


def test_canary_and_max_parallel_refuse_bad_numbers(fleet, built):
    fleet, _, _ = fleet
    for args in (["--canary", "-1"], ["--max-parallel", "0"], ["--canary", "x"]):
        code, out, err = run_ccrp_inprocess("deploy", *args, "-i", str(fleet.path), home=fleet.path.parent / "home")
        assert code == 2 and "Traceback" not in err, (args, err)


# -- deploy --rollback: the version each clone keeps ------------------------------------------------

def test_rollback_puts_back_the_version_the_last_deploy_replaced_and_again_goes_forward(fleet, built):
    """A deploy keeps the version it replaced (workspace, units, index, digest) on the clone;
    `--rollback` puts it back as a deploy would (its nodes restarted and checked, the state's
    digest); rolled back again, the clone runs the deployed version: the last two, in turn."""
    fleet, clones, old = fleet
    unit_before = clones.at("nao1", MAPPER).read_text()
    new = change_workspace(fleet)
    [deployed] = deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert deployed.action == "deployed"
    assert clones.at("nao1", "/opt/ccrp/workspace.last/setup.sh").read_text() == "v1"
    assert clones.at("nao1", "/var/lib/ccrp/deploy/last/digest").read_text().strip() == ""  # the snapshot's
    [dry] = deploy.rollback(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1", dry_run=True)
    assert (dry.action, dry.detail) == ("would roll back", f"software {new} -> {old}; nodes mapper"), dry
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v2"
    clones.execs.clear()
    [back] = deploy.rollback(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert (back.action, back.detail) == ("rolled back", f"software {new} -> {old}; nodes mapper"), back
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"
    assert clones.at("nao1", MAPPER).read_text() == unit_before
    assert json.loads(clones.at("nao1", INDEX).read_text())["software"] == old
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/current").exists()  # the snapshot's, as before the deploy
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/pending").exists()
    assert clones.scripts("nao1") == ["last", "restore", "commit"] and built == [new]  # nothing built
    assert ["systemctl", "restart", "ccrp-run-mapper.service"] in [argv for _, argv in clones.execs]
    assert Fleet.open(fleet.path).store.load_state().robots["nao1"].software == old
    # The version rolled back from is the one kept now: --rollback again goes forward.
    assert clones.at("nao1", "/opt/ccrp/workspace.last/setup.sh").read_text() == "v2"
    [forward] = deploy.rollback(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert (forward.action, forward.detail) == ("rolled back", f"software {old} -> {new}; nodes mapper"), forward
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v2"
    assert clones.at("nao1", "/var/lib/ccrp/deploy/current").read_text().strip() == new
    assert Fleet.open(fleet.path).store.load_state().robots["nao1"].software == new
    assert deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")[0].action == "current"


def test_rollback_of_a_run_list_change_keeps_the_workspace(fleet, built, tmp_path):
    fleet, clones, _ = fleet
    write_inventory(tmp_path, run=[{"name": "mapper", "command": ["mapper", "--fast"]}, {"name": "faces", "command": ["faces"]}])
    assert deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao2")[0].action == "deployed"
    assert not clones.at("nao2", "/opt/ccrp/workspace.last").exists()  # the same workspace
    [back] = deploy.rollback(Fleet.open(fleet.path), clones, lambda m: None, robot="nao2")
    assert back.action == "rolled back", back
    assert "--fast" not in clones.at("nao2", MAPPER).read_text()
    assert not clones.at("nao2", "/etc/systemd/system/ccrp-run-faces.service").exists()
    assert "disable --now ccrp-run-faces.service" in clones.calls("nao2")
    assert clones.at("nao2", "/opt/ccrp/workspace/setup.sh").read_text() == "v1"


def test_rollback_without_a_kept_version_fails_by_name_and_skips_in_a_fleet(fleet, built):
    fleet, clones, _ = fleet
    [named] = deploy.rollback(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert named.action == "failed" and "no previous version is kept" in named.detail, named
    results = deploy.rollback(Fleet.open(fleet.path), clones, lambda m: None)
    assert {r.action for r in results} == {"skipped"} and set(clones.scripts()) == {"last"}


def test_a_kept_version_whose_node_fails_puts_the_clone_back_on_the_deployed_one(fleet, built):
    fleet, clones, old = fleet
    new = change_workspace(fleet)
    assert deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")[0].action == "deployed"
    clones.states["ccrp-run-mapper.service"] = ("failed", "failed", 0)
    [back] = deploy.rollback(Fleet.open(fleet.path), clones, lambda m: None, robot="nao1")
    assert back.action == "failed" and "after the rollback" in back.detail and "rolled back" in back.detail, back
    assert clones.at("nao1", "/opt/ccrp/workspace/setup.sh").read_text() == "v2"
    assert clones.at("nao1", "/var/lib/ccrp/deploy/current").read_text().strip() == new
    assert not clones.at("nao1", "/var/lib/ccrp/deploy/pending").exists()
    assert Fleet.open(fleet.path).store.load_state().robots["nao1"].software == new != old


def test_rollback_refuses_a_canary(fleet, built):
    fleet, clones, _ = fleet
    code, out, err = run_ccrp_inprocess("deploy", "--rollback", "--canary", "1", "-i", str(fleet.path),
                                        home=fleet.path.parent / "home")
    assert code == 2 and "--rollback takes no --canary" in err and "Traceback" not in err, err


def test_the_install_space_goes_to_the_clones_gzipped():
    import base64
    import gzip

    tar = install_tar("print('mapper')\n" * 5000)
    sent = base64.b64decode(install_space.pushed(tar))
    assert sent[:2] == b"\x1f\x8b" and gzip.decompress(sent) == tar and len(sent) * 10 < len(tar)
    assert install_space.pushed(tar) == install_space.pushed(tar)  # no timestamp: the same bytes for the same space


# -- a clone not running when the deploy ran gets it when it starts ----------------------------------

def test_a_stopped_clone_is_pending_and_the_install_space_is_kept_for_it(fleet, built, monkeypatch):
    from ccrp_cli.ops import reconcile

    fleet, clones, old = fleet
    running = clones.query
    monkeypatch.setattr(clones, "query", lambda: {r: rec.model_copy(update={"state": CloneState.STOPPED})
                                                  if r == "nao2" else rec for r, rec in running().items()})
    new = change_workspace(fleet)
    results = {r.robot: r for r in deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, type_="nao")}
    assert results["nao1"].action == "deployed", results
    assert (results["nao2"].action, results["nao2"].detail) == (
        "skipped", f"not running: gets software {new} when it starts (ccrp clone start, or fleet up)")
    assert clones.scripts("nao2") == [] and built == [new]
    fleet = Fleet.open(fleet.path)
    state = fleet.store.load_state()
    assert state.deployed == new and state.robots["nao2"].software == old
    kept = fleet.store.root / "deploy" / f"{new}.tgz.b64"
    assert kept.stat().st_mode & 0o777 == 0o600 and install_space.saved(fleet, new) == kept.read_text()
    note = reconcile._software_note(state, "nao2", None, new, pending=True)
    assert note == f"pending: runs software {old}, gets the deployed {new} when it starts", note
    # Deployed again with nothing running to change: the kept install space serves, nothing is built.
    deploy.deploy(fleet, clones, lambda m: None, type_="nao")
    assert built == [new]


def test_a_stopped_clone_behind_gets_a_build_when_no_running_one_needs_it(fleet, built, monkeypatch):
    fleet, clones, old = fleet
    running = clones.query
    monkeypatch.setattr(clones, "query", lambda: {r: rec.model_copy(update={"state": CloneState.STOPPED})
                                                  if r == "nao2" else rec for r, rec in running().items()})
    state = fleet.store.load_state()
    state.robots["nao2"].software = "0123456789abcdef"  # ran another version when it stopped
    fleet.store.save_state(state)
    results = {r.robot: r for r in deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, type_="nao")}
    assert results["nao1"].action == "current" and results["nao2"].action == "skipped", results
    assert built == [old] and install_space.saved(Fleet.open(fleet.path), old) is not None


def test_the_fleet_keeps_the_last_two_install_spaces(fleet):
    fleet, _, _ = fleet
    for digest in ("a" * 16, "b" * 16, "c" * 16):
        install_space.save(fleet, digest, digest)
        time.sleep(0.01)
    assert sorted(p.name for p in (fleet.store.root / "deploy").iterdir()) == [f"{'b' * 16}.tgz.b64", f"{'c' * 16}.tgz.b64"]
    assert install_space.saved(fleet, "a" * 16) is None and install_space.saved(fleet, "c" * 16) == "c" * 16


def test_a_robot_whose_clone_failed_and_went_does_not_hold_the_deploy_back(fleet, built, monkeypatch):
    """A clone that failed at `fleet up` is deleted, its record keeping no packages: deploy refused the
    whole fleet for it ("does not record the apt/pip packages", on a real OpenStack)."""
    fleet, clones, _ = fleet
    running = clones.query
    monkeypatch.setattr(clones, "query", lambda: {r: rec for r, rec in running().items() if r != "nao2"})
    state = fleet.store.load_state()
    state.robots["nao2"].phase, state.robots["nao2"].packages, state.robots["nao2"].software = "failed", None, None
    fleet.store.save_state(state)
    new = change_workspace(fleet)
    results = {r.robot: r for r in deploy.deploy(Fleet.open(fleet.path), clones, lambda m: None, type_="nao")}
    assert results["nao1"].action == "deployed" and results["nao2"].action == "skipped", results
    assert "no running clone" in results["nao2"].detail and built == [new]


def test_the_build_runs_here_when_an_engine_answers_else_on_a_running_clone(monkeypatch):
    """--build-on auto: this host's Docker engine when it answers, else the first running clone of the
    deploy; `clone` always a clone; no running clone to build on is one line."""
    import ccrp_cli.providers as providers

    class Cloud:
        kind = "openstack"

    answers = []
    monkeypatch.setattr(providers, "local_engine_answers", lambda: answers[-1])
    answers.append(True)
    assert deploy.builder(Cloud(), "auto", ["nao1", "nao2"]) is None
    assert deploy.builder(Cloud(), "clone", ["nao1", "nao2"]) == "nao1"
    answers.append(False)
    assert deploy.builder(Cloud(), "auto", ["nao2"]) == "nao2"
    assert deploy.builder(Cloud(), "local", ["nao2"]) is None
    with pytest.raises(CcrpError, match="this host has no Docker engine, and no clone of this deploy is running"):
        deploy.builder(Cloud(), "auto", [])
