"""Images for the Docker backend: the base image (from Debian packages, since Docker Hub may be
unreachable), the golden clone image built from a snapshot recipe, and the fleet's snapshots
(images of this engine labelled with the fleet and its state)."""

from __future__ import annotations

import io
import re
import shlex
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Sequence

from ...errors import CcrpError
from ...models.layout import LOCALE_SETUP, WORKSPACE
from ...recipes import Platform
from ...resources import agent_source
from ...store import ensure_state_id, read_state_id
from ...templates import render, static
from ..base import LABEL_FLEET, LABEL_ROBOT, SnapshotRecord, owner_labels
from .archive import tar_files
from .client import DockerHost

DEFAULT_BASE = "ccrp/base:bookworm"
# Enough for systemd to boot and apt to work; the recipe adds the rest at `snapshot build`.
BASE_PACKAGES = ["ca-certificates", "systemd", "systemd-sysv"]
# A bare snapshot: just enough to boot cloud-init, which then installs the recipe at first boot.
BARE_PACKAGES = ["cloud-init", "locales"]


def build_base_image(client, tag: str, packages: list[str], progress=lambda msg: None) -> None:
    """Build `tag` with mmdebstrap (Debian bookworm minbase) and `docker import` it."""
    if shutil.which("mmdebstrap") is None:
        raise CcrpError(
            f"base image {tag} is missing and mmdebstrap is not installed to build it",
            hint="apt-get install mmdebstrap, or set provider.base_image to an image your registry has",
        )
    progress(f"building base image {tag} from Debian packages (mmdebstrap, about a minute)")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "rootfs.tar"
        argv = ["mmdebstrap", "--variant=minbase", f"--include={','.join(packages)}", "bookworm", str(out)]
        proc = subprocess.run(argv, capture_output=True, text=True)
        if proc.returncode != 0:
            last = (proc.stderr.strip().splitlines() or ["?"])[-1]
            raise CcrpError(f"mmdebstrap failed: {last}", hint="check that the Debian mirror is reachable")
        repo, _, tagname = tag.rpartition(":")
        with open(out, "rb") as fh:
            client.api.import_image_from_data(fh.read(), repository=repo, tag=tagname,
                                              changes=['CMD ["/lib/systemd/systemd"]'])


_ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
# A line saying what went wrong: a Python exception, a compiler's or CMake's error.
_ERROR_LINE = re.compile(r"\b[A-Z]\w*(Error|Exception)\b:|: (fatal )?error:|CMake Error|^E: ")


def step_error(output: str) -> str:
    """The line of a failed build step's output that says why: the last error-looking one, else
    the last line that is not Docker's own."""
    lines = [" ".join(_ANSI.sub("", line).split()) for line in output.splitlines()]
    lines = [line for line in lines if line and not line.startswith(("--->", "Removing intermediate", "Running in "))]
    errors = [line for line in lines if _ERROR_LINE.search(line)]
    return (errors or lines or [""])[-1][:300]


def ensure_base(client, base: str, plat: Platform, progress=lambda msg: None) -> None:
    """The image a clone image is built FROM: pulled, or for ccrp's own base built from Debian
    packages with the recipe's packages already in."""
    import docker

    try:
        client.images.get(base)
        return
    except docker.errors.ImageNotFound:
        pass
    if base != DEFAULT_BASE:
        progress(f"pulling base image {base}")
        try:
            client.images.pull(base)
        except Exception as exc:  # noqa: BLE001 - registry errors vary
            raise CcrpError(f"cannot pull base image {base}: {exc}", hint="check provider.base_image") from None
    else:
        build_base_image(client, base, sorted(set(BASE_PACKAGES + plat.packages)), progress)


def dockerfile(fleet: str, distro: str, base_image: str, plat: Platform, software=None, *, agents: Sequence[str]) -> str:
    """A ROS 1 image has the recipe's `pip` list in /usr/local and ccrp's `agents` (agent/<name>.py,
    as the core hands them: its services' image_agents; build_context carries them) in
    /usr/local/lib/ccrp; a ROS 2 distro's has its `pip` list (the ros-<distro>-* wheels) in a venv at
    /opt/ros/<distro> (docs/ros2.md) and no agents. The fleet's own software
    (workloads.SnapshotSoftware), when it has some, comes last (templates/docker/software.j2)."""
    from ...recipes import is_ros2

    prefix = f"/opt/ros/{distro}" if is_ros2(distro) and plat.pip else ""
    extra: dict = {"software": None}
    if software is not None and not software.empty:
        # Quoted: a RUN line is a shell's, where `numpy<2` reads a file "2" and `numpy>=1.24` writes one.
        extra = {"software": software, "sw_apt": software.apt, "sw_pip": [shlex.quote(p) for p in software.pip_install],
                 "build_apt": software.build_tools.apt, "tools_pip": software.build_tools.pip, "prefix": WORKSPACE,
                 "pip_command": f"{prefix}/bin/pip" if prefix else "PIP_BREAK_SYSTEM_PACKAGES=1 pip3",
                 "python_dirs": software.python_dirs,
                 "interfaces": software.interface_words}
    return render("docker/Dockerfile.j2", fleet=fleet, distro=distro, base_image=base_image, packages=plat.packages,
                  pip=plat.pip, locale_setup=LOCALE_SETUP, ros2_prefix=prefix, agents=[f"{a}.py" for a in agents], **extra)


def build_context(plat: Platform, progress=lambda msg: None, distro: str = "noetic", software=None, *,
                  agents: Sequence[str]) -> dict[str, bytes]:
    """Files the Dockerfile copies: the `agents` (as dockerfile was given them) and the wheels of the recipe's pip packages,
    downloaded here for the image's python (bookworm: 3.11) so the build needs no index. A ROS 2 distro's
    image has the wheels only (its agents are ROS 1 only so far), fetched with their own platform tags.
    With the fleet's software: its workspace and the wheels of its `pip` list, from the same cache."""
    tool = {"ccrp-topic": static("image/ccrp-topic").encode()}  # every image has it
    return tool | _recipe_context(plat, progress, distro, agents) | _software_context(software, progress, plat)


def _software_context(software, progress, plat: Platform) -> dict[str, bytes]:
    from . import wheels

    if software is None or software.empty:
        return {}
    files = {f"workspace/{rel}": data for rel, data in software.workspace}
    if software.build_tools.pip:  # the interface packages' build stage (templates/docker/software.j2)
        progress(f"fetching wheels of the workspace's build tools: {', '.join(software.build_tools.pip)}")
        files |= {f"tools-{name}": data for name, data in wheels.fetch(software.build_tools.pip, tuple(plat.wheel_platforms)).items()}
        files["interfaces-build.sh"] = static("image/interfaces-build.sh").encode()
    pip = software.pip_install
    if pip:
        progress(f"fetching wheels for the fleet's software: {', '.join(pip)}")
        files |= {f"software-{name}": data for name, data in wheels.fetch(pip, tuple(plat.wheel_platforms)).items()}
    return files


def _recipe_context(plat: Platform, progress, distro: str, agents: Sequence[str]) -> dict[str, bytes]:
    from ...recipes import is_ros2

    if not plat.pip:
        return {}
    progress(f"fetching wheels for the clone image: {', '.join(plat.pip)}")
    if is_ros2(distro):
        from .ros2 import venv_context

        return venv_context(plat)
    from . import wheels

    sources = {f"{name}.py": agent_source(name).encode() for name in agents}
    return sources | wheels.fetch(plat.pip, tuple(plat.wheel_platforms))


def build_clone_image(client, tag: str, text: str, labels: dict[str, str], progress=lambda msg: None,
                      files: dict[str, bytes] | None = None, what: str = "snapshot build") -> str:
    """docker build from an in-memory context: the Dockerfile and `files`. A failed step is one
    line: the error its tool printed (Docker itself only says "returned a non-zero code")."""
    entries = [("Dockerfile", text.encode(), 0o644), *((name, data, 0o644) for name, data in (files or {}).items())]
    buf = io.BytesIO(tar_files(entries))
    image_id = None
    step, said = "", ""  # the step running and what it printed (its tail)
    for chunk in client.api.build(fileobj=buf, custom_context=True, tag=tag, labels=labels, rm=True,
                                  forcerm=True, decode=True):
        if "error" in chunk:
            cause = step_error(said)
            if cause:
                raise CcrpError(f"{what} failed: {cause} (at {' '.join(step.split())[:80]})")
            raise CcrpError(f"{what} failed: {' '.join(chunk['error'].split())[:400]}")
        stream = chunk.get("stream", "")
        if stream.strip().startswith("Step "):
            step, said = stream.strip(), ""
            progress(step)
        else:
            said = (said + stream)[-20000:]
        if "aux" in chunk and "ID" in chunk["aux"]:
            image_id = chunk["aux"]["ID"]
    return image_id or client.images.get(tag).id


def build_snapshot_image(client, repo: str, fleet: str, distro: str, base: str, plat: Platform, agents: Sequence[str],
                         software, bare: bool, labels: dict[str, str], progress=lambda msg: None) -> str:
    """The clone image `repo:[bare-]<stamp>` built on this engine from `base` (ccrp's own is made
    from Debian packages when missing) with the recipe's platform, ccrp's `agents` (LocalBuild) and
    the fleet's `software` (None: none); returns its tag. A `bare` image has systemd and cloud-init only: its clones install the
    recipe at boot. The snapshot of the Docker backend, and the root file system of libvirt's."""
    import datetime as dt

    import docker

    if bare:
        base, plat = f"ccrp/base-bare:{distro}", plat.model_copy(update={"packages": BARE_PACKAGES, "pip": []})
        try:
            client.images.get(base)
        except docker.errors.ImageNotFound:
            build_base_image(client, base, BASE_PACKAGES + BARE_PACKAGES, progress)
    else:
        ensure_base(client, base, plat, progress)
    tag = f"{repo}:{'bare-' if bare else ''}{dt.datetime.now(dt.timezone.utc):%Y%m%d%H%M%S}"
    progress(f"building snapshot {tag} from {base}")
    labels = labels | {"ccrp-distro": distro, "ccrp-bare": str(bare).lower()}
    build_clone_image(client, tag, dockerfile(fleet, distro, base, plat, software, agents=agents), labels, progress,
                      build_context(plat, progress, distro, software, agents=agents))
    return tag


# -- the fleet's snapshots: images of this engine ------------------------------------------------------
def snapshot_labels(c: DockerHost, robot: str | None = None) -> dict[str, str]:
    """Owner labels of a snapshot image, with the state it belongs to (`ccrp gc` finds the
    images of deleted state directories by them)."""
    from .snapshot_images import state_labels

    return owner_labels(c.fleet, "snapshot", robot) | state_labels(c.state_dir, ensure_state_id(c.state_dir))


def snapshot_record(image) -> SnapshotRecord:
    return SnapshotRecord(
        id=image.id.removeprefix("sha256:")[:12],
        name=(image.tags or ["<untagged>"])[0],
        created=image.attrs.get("Created", "")[:19],
        source=image.labels.get(LABEL_ROBOT) or "build",
        size_mb=round(image.attrs.get("Size", 0) / 1e6, 1),
    )


def create_snapshot(c: DockerHost, robot: str, name: str) -> SnapshotRecord:
    container = c.running_container(robot)
    # The secrets volume is not part of a commit: the snapshot carries no key.
    repo, _, tag = name.rpartition(":")
    # Labels through the config, not a LABEL line: the state directory's path is taken as it
    # is (spaces, quotes, `$`), and these win over the clone's own labels the image inherits.
    image = container.commit(repository=repo, tag=tag, conf={"Labels": snapshot_labels(c, robot)})
    return snapshot_record(image)


def build_snapshot(c: DockerHost, repo: str, distro: str, base_image: str, plat, agents: tuple[str, ...],
                   software, digest: str, bare: bool, progress) -> SnapshotRecord:
    """Ability.LOCAL_BUILD: the clone image built on this engine (build_snapshot_image)."""
    tag = build_snapshot_image(c.engine, repo, c.fleet, distro, base_image, plat, agents, software, bare,
                               snapshot_labels(c) | {"ccrp-software": digest}, progress)
    return snapshot_record(c.engine.images.get(tag))


def list_snapshots(c: DockerHost) -> list[SnapshotRecord]:
    """This state's snapshots, and the fleet's from before images were labelled with their
    state: a fleet of the same name in another CCRP_HOME has its own (retention and gc of
    this one must not touch them)."""
    from .snapshot_images import LABEL_STATE_ID

    mine = read_state_id(c.state_dir)
    found = [i for i in c.engine.images.list(filters=c.filters("snapshot"))
             if i.labels.get(LABEL_STATE_ID) in (None, mine)]
    return sorted((snapshot_record(i) for i in found), key=lambda s: s.created)


def delete_snapshot(c: DockerHost, snapshot_id: str) -> None:
    try:
        image = c.engine.images.get(snapshot_id)
    except c.NotFound:
        raise CcrpError(f"snapshot {snapshot_id} not found", hint="ccrp snapshot list") from None
    if image.labels.get(LABEL_FLEET) != c.fleet:
        raise CcrpError(f"image {snapshot_id} is not a snapshot of fleet {c.fleet!r}")
    c.engine.images.remove(image.id, force=True)


def has_image(c: DockerHost, image: str) -> bool:
    try:
        c.engine.images.get(image)
        return True
    except c.NotFound:
        return False


def ensure_image(c: DockerHost, image: str) -> None:
    try:
        c.engine.images.get(image)
    except c.NotFound:
        raise CcrpError(f"snapshot image {image} not found", hint="run `ccrp snapshot build -i INVENTORY`") from None
