"""No privilege out of the user's install space (issue 39, part 3; docs/security.md): it is unpacked
and built as root, so a 4755 file would come out root's setuid program on every clone. ccrp deploy's
stage (DEPLOY_SH), the Docker snapshot's layers (templates/docker/software.j2) and the clouds' bake
(templates/image/software-bake.sh) strip setuid and setgid bits and refuse device files and FIFOs.
The ROS 1 master runs with the nodes' hardening, as a user of its own."""

from __future__ import annotations

import io
import os
import re
import stat
import subprocess
import tarfile
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from ccrp_cli.errors import CcrpError
from ccrp_cli.fleet import clone_view
from ccrp_cli.ops import deploy, install_space
from ccrp_cli.render import cloudinit
from ccrp_cli.services.registry import boots
from ccrp_cli.templates import render
from tests.conftest import ROOT

MOVED = re.compile(r"(/etc/systemd/system|/etc/ccrp|/opt/ccrp|/var/lib/ccrp)")


def _tar(members: list[tuple[str, bytes | str | None, int]]) -> bytes:
    """An install space as deploy reads it out of the image (top directory `workspace/`): (name,
    bytes of a file | a link's target | None for a directory | "fifo", mode)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data, mode in [("workspace", None, 0o755), *members]:
            info = tarfile.TarInfo(name)
            info.mode = mode
            if data is None:
                info.type = tarfile.DIRTYPE
            elif data == "fifo":
                info.type = tarfile.FIFOTYPE
            elif isinstance(data, str):
                info.type, info.linkname = tarfile.SYMTYPE, data
            if isinstance(data, bytes):
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
            else:
                tar.addfile(info)
    return buf.getvalue()


class Clone:
    """A clone that is a directory: DEPLOY_SH runs for real with the clone's paths moved under it."""

    def __init__(self, root: Path, path: str = "/usr/bin:/bin") -> None:
        self.root = root
        self.transport = self
        self.path = path  # a directory of stand-ins first: what the script asks of systemctl

    def at(self, path: str) -> Path:
        return self.root / path.lstrip("/")

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        base = str(self.root)
        proc = subprocess.run([MOVED.sub(lambda m: base + m.group(1), w) for w in argv], capture_output=True,
                              text=True, check=False, env={"PATH": self.path})
        return proc.returncode, (proc.stdout + proc.stderr).replace(base, "")


def _stage(tmp_path: Path, members) -> Clone:
    clone = Clone(tmp_path / "clone")
    pushed = clone.at(f"{install_space.DEPLOY_DIR}/d1.tar.b64")
    pushed.parent.mkdir(parents=True)
    pushed.write_text(install_space.pushed(_tar(members)))
    install_space.script(clone, "nao1", "stage", "d1")
    return clone


def test_deploy_strips_setuid_and_setgid_bits_from_the_install_space(tmp_path):
    outside = tmp_path / "passwd"  # a setuid program elsewhere, which a link in the tar names
    outside.write_text("x")
    outside.chmod(0o4755)
    clone = _stage(tmp_path, [("workspace/bin", None, 0o2775), ("workspace/bin/tool", b"#!/bin/sh\n", 0o4755),
                              ("workspace/bin/group", b"#!/bin/sh\n", 0o2711), ("workspace/bin/both", b"x", 0o6750),
                              ("workspace/bin/link", str(outside), 0o777)])
    new = clone.at("/opt/ccrp/workspace.new")
    modes = {p.name: stat.S_IMODE(p.lstat().st_mode) for p in (new / "bin").iterdir() if not p.is_symlink()}
    assert modes == {"tool": 0o755, "group": 0o711, "both": 0o750}, {k: oct(v) for k, v in modes.items()}
    assert stat.S_IMODE((new / "bin").stat().st_mode) == 0o775
    assert stat.S_IMODE(new.stat().st_mode) == 0o755  # readable by the nodes once swapped in
    assert stat.S_IMODE(outside.stat().st_mode) == 0o4755  # a link is never followed
    assert not clone.at(f"{install_space.DEPLOY_DIR}/d1.tar.b64").exists()


def test_deploy_refuses_a_fifo_in_the_install_space_in_one_line(tmp_path):
    with pytest.raises(CcrpError) as err:
        _stage(tmp_path, [("workspace/share", None, 0o755), ("workspace/share/pipe", "fifo", 0o666)])
    assert str(err.value) == ("deploy step stage failed on robot 'nao1''s clone: the install space holds share/pipe, "
                              "a device file or FIFO: refused (only files, directories and links)")
    assert not (tmp_path / "clone" / "opt" / "ccrp" / "workspace.new").exists()


def _tree(root: Path) -> Path:
    """An install space as a build leaves it: a setuid, a setgid program and a plain one."""
    (root / "lib" / "pkg").mkdir(parents=True)
    for name, mode in (("su", 0o4755), ("sg", 0o2755), ("plain", 0o755)):
        (root / "lib" / "pkg" / name).write_text("x")
        (root / "lib" / "pkg" / name).chmod(mode)
    return root


def _modes(root: Path) -> dict[str, int]:
    return {p.name: stat.S_IMODE(p.stat().st_mode) for p in (root / "lib" / "pkg").iterdir()}


@pytest.mark.parametrize("build_type", ["catkin", "ament"])
def test_the_docker_snapshot_strips_setuid_bits_and_refuses_a_fifo(tmp_path, build_type):
    prefix = _tree(tmp_path / "ws")
    text = render("docker/software.j2", software=SimpleNamespace(build_type=build_type, digest="d1"), prefix=str(prefix),
                  build_apt=["catkin"], sw_apt=[], sw_pip=[], pip_command="pip", python_dirs=["src/a"], interfaces=[],
                  ros2_prefix="/opt/ros/jazzy")
    # The build's RUN step after the install: the lines from the check on, as its shell runs them.
    [check] = [line.strip().removeprefix("&& ").removesuffix(" \\") for line in text.splitlines()
               if line.strip().startswith(f"&& bad=$(find {prefix} ")]
    subprocess.run(["sh", "-ec", check], check=True)
    assert _modes(prefix) == {"su": 0o755, "sg": 0o755, "plain": 0o755}
    os.mkfifo(prefix / "lib" / "pkg" / "pipe")
    proc = subprocess.run(["sh", "-ec", check], capture_output=True, text=True)
    assert proc.returncode == 1 and proc.stderr == (f"the install space holds {prefix}/lib/pkg/pipe, a device file or "
                                                    "FIFO: refused (only files, directories and links)\n"), proc.stderr


def test_the_clouds_bake_strips_setuid_bits_and_refuses_a_fifo(tmp_path):
    prefix = _tree(tmp_path / "ws")
    script = (ROOT / "templates" / "image" / "software-bake.sh").read_text()
    # The step after the build, run on its own with W moved (the rest installs packages as root).
    block = script[script.index('if [ -d "$R$W" ]; then'):script.index('if [ -n "$CCRP_OUT" ]; then\n  mkdir')]
    run = lambda: subprocess.run(["sh", "-euc", f'step() {{ echo "== $*"; }}; R=""; W={prefix}\n{block}'],  # noqa: E731
                                 capture_output=True, text=True)
    assert run().returncode == 0
    assert _modes(prefix) == {"su": 0o755, "sg": 0o755, "plain": 0o755}
    os.mkfifo(prefix / "lib" / "pkg" / "pipe")
    proc = run()
    assert proc.returncode == 1 and "the install space holds" in proc.stderr and "pipe, a device file or FIFO" in proc.stderr


def test_a_deploys_build_on_a_clone_writes_its_install_space_as_a_tar_of_workspace(tmp_path):
    """`ccrp deploy --build-on clone`: the install space built under the root R goes into CCRP_OUT
    (top directory workspace/, as Docker's build gives it), the build's directory goes, and the bake's
    last steps (the login taken away, sync) do not run on a clone."""
    import tarfile

    root = tmp_path / "root"
    _tree(root / "opt" / "ccrp" / "workspace")
    script = (ROOT / "templates" / "image" / "software-bake.sh").read_text()
    block = script[script.index('if [ -n "$CCRP_OUT" ]; then\n  mkdir'):]
    out, bake = tmp_path / "out.tgz", tmp_path / "bake"
    bake.mkdir()
    proc = subprocess.run(["sh", "-euc", f'step() {{ echo "== $*"; }}; R={root}; W=/opt/ccrp/workspace; B={bake}; '
                                         f'CCRP_OUT={out}; CCRP_LOGIN=nobody-here\n{block}'], capture_output=True, text=True)
    assert proc.returncode == 0 and proc.stdout.strip().splitlines()[-1] == "ccrp-software built", proc
    assert "login removed" not in proc.stdout and not bake.exists()
    with tarfile.open(out) as tar:
        names = tar.getnames()
    assert names[0] == "workspace" and "workspace/lib/pkg/plain" in names, names


def test_the_clouds_bake_writes_the_install_space_back_before_it_says_built():
    """The capture follows "ccrp-software built" at once, and a real Nova captured the builder with
    the workspace's setup.sh still in its page cache (docs/openstack.md, difference 7)."""
    lines = [line.strip() for line in (ROOT / "templates" / "image" / "software-bake.sh").read_text().splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    assert lines[-2:] == ["sync", 'echo "ccrp-software built"']


def test_the_ros1_master_has_the_nodes_hardening_and_a_home_they_cannot_write(lab):
    data = yaml.safe_load(cloudinit.user_data(clone_view(lab, lab.store.load_state(), "nao1"), boots()))
    unit = next(f["content"] for f in data["write_files"] if f["path"] == "/etc/systemd/system/ccrp-rosmaster.service")
    settings = dict(line.split("=", 1) for line in unit.splitlines() if "=" in line and not line.startswith("#"))
    # A user of its own, not the nodes' `ros`: its home (~/.ros, ~/.local) is nothing they can write.
    assert settings["User"] == cloudinit.MASTER_USER != "ros"
    assert cloudinit.MASTER_USER in {u["name"] for u in data["users"]}
    assert settings["StateDirectory"] == "ccrp-rosmaster" and settings["StateDirectoryMode"] == "0700"
    env = dict(word.split("=", 1) for word in settings["Environment"].split())
    assert env == {"HOME": "/var/lib/ccrp-rosmaster", "ROS_HOME": "/var/lib/ccrp-rosmaster", "PYTHONNOUSERSITE": "1"}
    for key, value in {"NoNewPrivileges": "yes", "ProtectSystem": "strict", "ProtectHome": "yes", "PrivateTmp": "yes",
                       "RestrictSUIDSGID": "yes"}.items():
        assert settings.get(key) == value, (key, unit)
    assert settings["ExecStart"] == "/usr/local/lib/ccrp/ros-run roscore --port ${ROS_MASTER_PORT}"  # no workspace


# -- only what a clone lacks: install_space.delta and stage's delta ----------------------------------

def _probed(clone: Clone) -> dict[str, tuple[str, str]]:
    """What deploy's probe reads of the clone's install space."""
    out = install_space.script(clone, "nao1", "probe")
    return deploy.workspace_files(out.partition("\n== workspace\n")[2])


def test_a_clone_is_sent_only_the_files_it_lacks_and_ends_with_the_whole_version(tmp_path):
    import hashlib

    old = _tar([("workspace/same.py", b"same", 0o644), ("workspace/changed.py", b"v1", 0o644),
                ("workspace/chmod.sh", b"#!/bin/sh\n", 0o644), ("workspace/gone.py", b"x", 0o644),
                ("workspace/olddir", None, 0o755), ("workspace/olddir/f", b"f", 0o644),
                ("workspace/odd\nname", b"n", 0o644)])
    new_members = [("workspace/same.py", b"same", 0o644), ("workspace/changed.py", b"v2", 0o644),
                   ("workspace/chmod.sh", b"#!/bin/sh\n", 0o755), ("workspace/lib", None, 0o755),
                   ("workspace/lib/new.py", b"new", 0o644), ("workspace/lib/link", "new.py", 0o777),
                   ("workspace/odd\nname", b"n", 0o644)]
    clone = Clone(tmp_path / "clone")
    pushed = clone.at(f"{install_space.DEPLOY_DIR}/d1.tar.b64")
    pushed.parent.mkdir(parents=True)
    pushed.write_text(install_space.pushed(old))
    for action in (("stage", "d1"), ("swap", "d1"), ("commit",)):
        install_space.script(clone, "nao1", *action)
    have = _probed(clone)
    assert have["./same.py"] == (hashlib.sha256(b"same").hexdigest(), "644") and len(have) == 5, have  # odd\nname: unread
    sent = tarfile.open(fileobj=io.BytesIO(install_space.delta(_tar(new_members), have)))
    files = {m.name: sent.extractfile(m).read() for m in sent.getmembers() if m.isfile()}
    assert set(files) == {"workspace/changed.py", "workspace/chmod.sh", "workspace/lib/new.py", "workspace/odd\nname",
                          "workspace/.ccrp-manifest"}, set(files)  # not same.py
    assert files["workspace/.ccrp-manifest"].split(b"\0")[:-1] == [
        b"./same.py", b"./changed.py", b"./chmod.sh", b"./lib", b"./lib/new.py", b"./lib/link", b"./odd\nname"]
    pushed.with_name("d2.tar.b64").write_text(install_space.pushed(install_space.delta(_tar(new_members), have)))
    install_space.script(clone, "nao1", "stage", "d2", "delta")
    staged = clone.at("/opt/ccrp/workspace.new")
    got = {str(p.relative_to(staged)): (p.readlink().as_posix() if p.is_symlink() else p.read_bytes() if p.is_file() else None,
                                        stat.S_IMODE(p.lstat().st_mode)) for p in staged.rglob("*")}
    assert got == {"same.py": (b"same", 0o644), "changed.py": (b"v2", 0o644), "chmod.sh": (b"#!/bin/sh\n", 0o755),
                   "lib": (None, 0o755), "lib/new.py": (b"new", 0o644), "lib/link": ("new.py", 0o777),
                   "odd\nname": (b"n", 0o644)}, got
    assert stat.S_IMODE(staged.stat().st_mode) == 0o755
    assert sorted(p.name for p in clone.at(install_space.DEPLOY_DIR).iterdir()) == ["current", "last", "prev"]


def test_the_relay_restarts_when_a_swap_or_a_rollback_changes_the_interface_packages(tmp_path):
    """The relay loads the workspace's message types once: a deploy (or its rollback) that changes
    the build's list of them restarts it; one that changes only a node's code does not."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "systemctl.log"
    (bin_dir / "systemctl").write_text(f'#!/bin/sh\necho "$*" >> {calls}\n')
    (bin_dir / "systemctl").chmod(0o755)
    clone = Clone(tmp_path / "clone", path=f"{bin_dir}:/usr/bin:/bin")
    pushed = clone.at(f"{install_space.DEPLOY_DIR}/x")
    pushed.parent.mkdir(parents=True)
    listing = "workspace/share/ccrp/interfaces.json"

    def deploy(digest: str, members) -> list[str]:
        calls.write_text("")
        pushed.with_name(f"{digest}.tar.b64").write_text(install_space.pushed(_tar(
            [("workspace/share", None, 0o755), ("workspace/share/ccrp", None, 0o755), *members])))
        for action in (("stage", digest), ("swap", digest)):
            install_space.script(clone, "nao1", *action)
        return calls.read_text().splitlines()

    restart = ["try-restart ccrp-relay.service"]
    assert deploy("d1", [("workspace/node.py", b"v1", 0o644)]) == []  # no interface package: nothing
    install_space.script(clone, "nao1", "commit")
    assert deploy("d2", [("workspace/node.py", b"v1", 0o644), (listing, b'{"packages": {"a": 1}}', 0o644)]) == restart
    install_space.script(clone, "nao1", "commit")
    assert deploy("d3", [("workspace/node.py", b"v2", 0o644), (listing, b'{"packages": {"a": 1}}', 0o644)]) == []
    install_space.script(clone, "nao1", "commit")
    assert deploy("d4", [("workspace/node.py", b"v2", 0o644), (listing, b'{"packages": {"a": 2}}', 0o644)]) == restart
    calls.write_text("")
    install_space.script(clone, "nao1", "rollback")  # its nodes failed: d3's types back, the relay with them
    assert "try-restart ccrp-relay.service" in calls.read_text().splitlines()


def test_a_delta_that_does_not_unpack_is_followed_by_the_whole_install_space(tmp_path):
    """A path that was a directory and is a file now: the delta over the copy cannot unpack, and
    deploy sends the whole install space."""
    from ccrp_cli.ops.deploy import Change, apply

    clone = Clone(tmp_path / "clone")
    pushed = clone.at(f"{install_space.DEPLOY_DIR}/d1.tar.b64")
    pushed.parent.mkdir(parents=True)
    pushed.write_text(install_space.pushed(_tar([("workspace/x", None, 0o755), ("workspace/x/y", b"y", 0o644)])))
    for action in (("stage", "d1"), ("swap", "d1"), ("commit",)):
        install_space.script(clone, "nao1", *action)
    clone.push_files = lambda robot, files, restart=(): [clone.at(f.dest).write_text(f.content) for f in files]
    said: list[str] = []
    change = Change("nao1", "d1", "d2", [], {}, _probed(clone))
    writer = SimpleNamespace(state=SimpleNamespace(robots={}), update=lambda *a, **k: None)
    tar = _tar([("workspace/x", b"now a file", 0o644)])
    apply(clone, writer, change, tar, said.append)
    assert any("sending the whole install space" in line for line in said), said
    assert clone.at("/opt/ccrp/workspace/x").read_bytes() == b"now a file"
