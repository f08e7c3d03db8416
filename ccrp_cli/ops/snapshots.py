"""Golden images: build from the recipe, capture a configured clone, list, delete."""

from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING, Callable, Protocol, cast

from ..errors import CcrpError
from ..fleet import Fleet
from ..models.addressing import builder_ip
from ..providers.base import SnapshotRecord
from ..services.workloads import NO_SOFTWARE, SnapshotSoftware

if TYPE_CHECKING:
    from ..models.state import FleetState
    from ..providers.base import Bake, CloneRecord, Images, Lifecycle, LocalBuild, Provider, Reaches

    class Baker(Reaches, Bake, Protocol):
        """What `snapshot bake` asks of a provider with Ability.BAKE beside the lifecycle."""

Progress = Callable[[str], None]


def _stamp() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d%H%M%S")


def image_repo(fleet: Fleet) -> str:
    return f"ccrp/{fleet.name}-clone"


def build(fleet: Fleet, provider: Provider, progress: Progress, bare: bool = False) -> SnapshotRecord:
    """Build the golden clone image on this host (Ability.LOCAL_BUILD: the provider's
    build_snapshot) and record it for new clones. A `bare` snapshot has only systemd and
    cloud-init: its clones install the recipe's packages at boot, as a clone started from a stock
    cloud image would (slower: the reason for snapshots, see bench/)."""
    from ..providers import info
    from ..recipes import platform
    from ..services.registry import image_agents
    from ..services.workloads import packages_record, snapshot_software

    inv = fleet.inventory
    plat = platform(inv.ros.distro, info(provider.kind).platform)
    # The fleet's own software, read and checked before anything is built (a bare snapshot has none:
    # its clones install ccrp's recipe at boot, and fleet up then refuses an inventory with software).
    software = None if bare else snapshot_software(inv, fleet.path)
    digest = software.digest if software is not None else NO_SOFTWARE
    # The agents the image holds are the services' to say (Boot.image_agents); the provider only builds.
    builder = cast("LocalBuild", provider)  # Ability.LOCAL_BUILD: `snapshot build` requires it (cli/options.py)
    record = builder.build_snapshot(image_repo(fleet), inv.ros.distro, plat, image_agents(), software, digest, bare,
                                    progress)
    # What `ccrp deploy` cannot change on a clone made from it (apt, pip): it compares them.
    held = {} if software is None else {"packages": packages_record(software)}
    _use(fleet, record, bare, software=digest, **held)
    return record


def _use(fleet: Fleet, record: SnapshotRecord, bare: bool = False, image: str | None = None, **extra: str) -> None:
    state = fleet.store.load_state()
    state.snapshot = {"image": image or record.name, "id": record.id, "source": record.source, **extra}
    if bare:
        state.snapshot["bare"] = "true"
    fleet.store.save_state(state)


# -- clouds: bake a snapshot on a builder instance ----------------------------------------------------

BUILDER = "snapshot-builder"  # its robot label: the hyphen keeps it out of robot names' alphabet
def bake(fleet: Fleet, provider: Provider, progress: Progress, base_image: str | None = None, timeout: float = 1800,
         poll: float = 10) -> SnapshotRecord:
    """Boot a builder instance from a stock Debian 12 cloud image with user-data that installs the
    recipe, wait until its console proves the install finished, capture it, and record the snapshot
    for new clones. The builder is terminated in every case (failure, timeout, Ctrl-C)."""
    import secrets

    from ..errors import InputError
    from ..providers import Ability, info, require
    from ..providers.base import CloneSpec
    from ..recipes import platform
    from ..render.cloudinit import bake_proofs, builder_user_data

    inv = fleet.inventory
    kind = inv.provider.kind
    require(kind, Ability.BAKE, hint=f"on {kind} the golden image is built locally: `ccrp snapshot build`")
    baker = cast("Baker", provider)  # what Ability.BAKE adds, required just above
    from ..services.registry import image_agents
    from ..services.workloads import packages_record, snapshot_software

    # The fleet's own software, read and checked before any builder starts.
    software = snapshot_software(inv, fleet.path)
    base = base_image or inv.provider.bake_image()
    if base is None and platform(inv.ros.distro, inv.clone_platform).ros_installed:
        # The stock Debian image has no ROS 2 to use: the platform is the user's own image.
        raise InputError(f"ros.platform {inv.ros.platform} bakes from your image with ROS {inv.ros.distro} installed "
                         f"under /opt/ros/{inv.ros.distro}", hint="pass --base-image, or set provider.image")
    base = base or info(kind).bake_base  # the stock Debian 12 image of the cloud
    # A cloud may name its images indirectly (AWS: an SSM parameter): the state records what was used.
    base = provider.resolve_image(base)
    if not provider.has_image(base):
        raise InputError(f"base image {base} not found on {kind}", hint=info(kind).bake_base_hint)
    token = secrets.token_hex(8)
    # With software, ccrp logs in to build it after cloud-init: the builder's login gets the key.
    user_data = builder_user_data(inv, token, image_agents(), login_keys=None if software.empty else provider.login_keys())
    info(kind).fit_user_data(user_data)
    spec = CloneSpec(robot=BUILDER, hostname="ccrp-builder", image=base, user_data=user_data,
                     instance_id=f"{fleet.name}-builder-{token}", common_ip=str(builder_ip(inv)), role="builder")
    provider.bootstrap()
    progress(f"booting the builder from {base}; it installs ROS {inv.ros.distro} and the recipe (10-20 min)")
    try:
        builder = provider.run_instance(spec)
        _wait_baked(baker, token, bake_proofs(inv), timeout, poll, progress)
        if not software.empty:
            install_software(baker, builder, software, progress, timeout)
        name = f"ccrp-{fleet.name}-{inv.ros.distro}-{_stamp()}"
        progress(f"capturing snapshot {name}")
        record = provider.create_snapshot(BUILDER, name)
    except BaseException:
        _terminate_builder(provider, progress, failing=True)
        raise
    _terminate_builder(provider, progress, failing=False)
    image = record.name if info(kind).image_ref == "name" else record.id  # what run_instance is given
    # As `snapshot build` records it: fleet up refuses a snapshot whose software is not the
    # inventory's, fleet plan names clones made with another, deploy compares the packages.
    held = {} if software.empty else {"packages": packages_record(software)}
    _use(fleet, record, bare=False, image=image, region=inv.provider.place(), base=base, name=record.name,
         software=software.digest, **held)
    return record


BAKE_DIR = "/var/lib/ccrp/bake"  # on the builder: the workspace's tar; removed by the build


def software_env(software: SnapshotSoftware) -> dict[str, str]:
    """What templates/image/software-bake.sh is given: the same lists the Docker snapshot's
    software layers take (providers/docker/images.py dockerfile)."""
    from ..recipes import is_ros2
    from ..render.cloudinit import ros2_prefix
    from ..models.layout import LOGIN_USER

    ros2 = is_ros2(software.distro)
    prefix = ros2_prefix(software.distro)
    return {
        "CCRP_BUILD": software.build_type or "none",
        "CCRP_APT": " ".join(software.apt),
        "CCRP_BUILD_APT": " ".join(software.build_tools.apt),
        "CCRP_PIP": " ".join(software.pip_install),
        "CCRP_PIP_CMD": f"{prefix}/bin/pip" if ros2 else "env PIP_BREAK_SYSTEM_PACKAGES=1 pip3",
        "CCRP_PYTHON": f"{prefix}/bin/python" if ros2 else "python3",
        "CCRP_DIRS": " ".join(software.python_dirs),
        "CCRP_IFACE": " ".join(software.interface_words),
        "CCRP_TOOLS_PIP": " ".join(software.build_tools.pip),
        "CCRP_LOGIN": LOGIN_USER,
    }


def workspace_tar(software: SnapshotSoftware) -> bytes:
    """The workspace's source files (what its digest covers) as a tar, and under ccrp-tools/ the
    wheels of its build tools (fetched here: the machine building it needs no index for them)."""
    import io
    import tarfile

    files = list(software.workspace)
    if software.build_tools.pip:
        from ..providers import fetch_wheels
        from ..recipes import platform

        plat = platform(software.distro, software.platform)
        files += [(f"ccrp-tools/{name.rsplit('/', 1)[-1]}", data)
                  for name, data in fetch_wheels(software.build_tools.pip, tuple(plat.wheel_platforms)).items()]
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tar:
        for rel, data in files:
            info = tarfile.TarInfo(rel)
            info.size, info.mode = len(data), 0o644
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def install_software(provider: Baker, builder: CloneRecord, software: SnapshotSoftware, progress: Progress, timeout: float) -> None:
    """The fleet's software on the builder, over SSH after cloud-init installed the recipe (user-data
    has a size limit, and the workspace is the user's whole source): its workspace pushed as a
    root-only file, then templates/image/software-bake.sh installs the packages, builds it into
    /opt/ccrp/workspace and takes the builder's login away."""
    import time

    t0 = time.monotonic()
    progress(f"building software {software.digest} on the builder")
    provider.connect(BUILDER, builder)
    run_software_script(provider, BUILDER, software, software_env(software), "the builder", timeout)
    progress(f"software {software.digest} built on the builder after {time.monotonic() - t0:.0f} s")


def run_software_script(provider: Reaches, robot: str, software: SnapshotSoftware, env: dict[str, str], where: str,
                        timeout: float) -> None:
    """templates/image/software-bake.sh on robot's machine (a bake's builder, or the clone `ccrp
    deploy` builds on) with `env`, the workspace's sources pushed first as a root-only file; a
    failure is one line naming the step and the tools' error."""
    import base64

    from ..render.files import BundleFile
    from ..templates import static

    if software.build_type is not None:
        provider.transport.exec(robot, ["mkdir", "-p", "-m", "0700", BAKE_DIR], timeout=30)
        tar = base64.b64encode(workspace_tar(software)).decode()
        provider.transport.push_files(robot, [BundleFile("workspace.tar.b64", tar, 0o600, f"{BAKE_DIR}/workspace.tar.b64")],
                                      restart=[])
    words = [f"{k}={v}" for k, v in env.items()]
    script = static("image/interfaces-build.sh") + static("image/software-bake.sh")  # the first defines build_interfaces
    rc, out = provider.transport.exec(robot, ["env", *words, "sh", "-c", script, "ccrp-software"],
                                      timeout=timeout)
    if rc != 0 or "ccrp-software built" not in out:
        lines = [line.strip() for line in out.strip().splitlines() if line.strip()]
        steps = [line[3:] for line in lines if line.startswith("== ")]
        raise CcrpError(f"{where} could not build the software (at {steps[-1] if steps else 'the start'}): {_why(lines)}",
                        hint="the same recipe builds on Docker: `ccrp snapshot build` on a Docker inventory shows "
                             "the error faster; check software.apt/pip and the workspace")


def _why(lines: list[str]) -> str:
    """The first line saying error (CMake's, apt's E:, pip's ERROR:) and the last three: the tools'
    own summary lines ("Invoking cmake failed", "finished after") rarely say why."""
    import re

    first = next((line for line in lines if re.search(r"\berror\b|(^|\s)E: ", line, re.IGNORECASE)), None)
    return " | ".join(([first] if first and first not in lines[-3:] else []) + lines[-3:])[-500:]


def _wait_baked(provider: Bake, token: str, proofs: list[str], timeout: float, poll: float, progress: Progress) -> None:
    """Until the builder's console shows cloud-init's final message; then every install proof must be there."""
    import re
    import time

    from ..retry import PollTimeout
    from ..retry import poll as poll_until

    # "$UPTIME" stays literal in the user-data: only cloud-init's own line has a number there.
    final = re.compile(rf"ccrp-bake {token} finished after [0-9.]+ s")

    def finished() -> tuple[bool, str]:
        console = provider.console_output(BUILDER) or ""
        return bool(final.search(console)), console

    t0 = time.monotonic()
    try:
        console = poll_until(finished, timeout=timeout, interval=poll,
                             progress=lambda elapsed: progress(f"builder still installing ({elapsed:.0f} s)"))
    except PollTimeout:
        raise CcrpError(f"the builder did not finish within {timeout:.0f} s",
                        hint="look at its console output; a larger --timeout helps on slow mirrors") from None
    missing = [p for p in proofs if f"ccrp-bake {token} {p}-ok" not in console]
    if missing:
        # What cloud-init ran printed (the kernel's lines and cloud-init's network tables aside).
        said = [line.strip() for line in console.splitlines() if "cloud-init[" in line and "ci-info:" not in line]
        raise CcrpError(f"the builder finished but its {' and '.join(missing)} install failed: {_why(said)}",
                        hint="check that the base image is Debian 12 and can reach deb.debian.org and PyPI")
    progress(f"builder finished installing after {time.monotonic() - t0:.0f} s")


def _terminate_builder(provider: Lifecycle, progress: Progress, failing: bool) -> None:
    try:
        provider.terminate(BUILDER)
        progress("builder terminated")
    except Exception as exc:  # noqa: BLE001 - reported, and gc finds the instance by its labels
        message = f"could not terminate the builder instance ({exc})"
        if not failing:
            raise CcrpError(message, hint="`ccrp gc -i INVENTORY` removes it") from None
        # Keep the error that brought us here; this one is only reported.
        progress(f"warning: {message}; `ccrp gc -i INVENTORY` removes it")


# -- retention -------------------------------------------------------------------------------------

def in_use(state: FleetState) -> dict[str, list[str]] | None:
    """Snapshot (name or id) -> who uses it: "new clones" for the recorded one, and the robots
    whose clone was created from it, and the entry gateway's. None when a clone's or the gateway's
    snapshot is not known (made before ccrp recorded it): then nothing may be deleted."""
    used: dict[str, list[str]] = {}
    recorded = state.snapshot or {}
    for key in ("image", "id"):
        if recorded.get(key):
            used.setdefault(recorded[key], []).append("new clones")
    for robot, rec in sorted(state.robots.items()):
        if rec.provider_id:
            if not rec.image:
                return None
            used.setdefault(rec.image, []).append(robot)
    if state.gateway is not None:
        if not state.gateway.image:
            return None
        used.setdefault(state.gateway.image, []).append("entry gateway")
    return used


def users(record: SnapshotRecord, used: dict[str, list[str]] | None) -> list[str]:
    if used is None:
        return ["(unknown)"]
    return sorted({u for key in (record.id, record.name) for u in used.get(key, [])}, key=lambda u: (u != "new clones", u))


def surplus(state: FleetState, snapshots: list[SnapshotRecord], keep: int) -> list[SnapshotRecord]:
    """What retention removes: beyond the `keep` newest, every snapshot no clone runs from and
    new clones do not get."""
    used = in_use(state)
    if used is None:
        return []
    newest = sorted(snapshots, key=lambda s: s.created, reverse=True)
    return [s for i, s in enumerate(newest) if i >= keep and not users(s, used)]


def retain(fleet: Fleet, provider: Images, progress: Progress) -> list[str]:
    """Delete the snapshots retention does not keep (after a new one was recorded)."""
    keep = fleet.inventory.snapshots.keep
    state = fleet.store.load_state()
    if in_use(state) is None:
        progress("kept every snapshot: a clone's snapshot is not recorded (it predates retention); "
                 "they are pruned once every clone was created by this version")
        return []
    removed = []
    for record in surplus(state, provider.list_snapshots(), keep):
        provider.delete_snapshot(record.id)
        removed.append(record.name)
        progress(f"removed snapshot {record.name} (snapshots.keep is {keep}; no clone runs from it)")
    return removed


def create(fleet: Fleet, provider: Images, robot: str, use: bool) -> SnapshotRecord:
    record = provider.create_snapshot(robot, f"{image_repo(fleet)}:{robot}-{_stamp()}")
    if use:
        _use(fleet, record)
    return record


def delete(fleet: Fleet, provider: Images, snapshot: str, force: bool) -> None:
    state = fleet.store.load_state()
    current = state.snapshot or {}
    if snapshot in (current.get("image"), current.get("id")) and not force:
        raise CcrpError(f"snapshot {snapshot} is the one new clones are created from", hint="pass --force to delete it anyway")
    provider.delete_snapshot(snapshot)
    if snapshot in (current.get("image"), current.get("id")):
        state.snapshot = None
        fleet.store.save_state(state)


def snapshot_build(fleet: Fleet, provider: Provider, say: Progress, if_missing: bool = False,
                   bare: bool = False) -> SnapshotRecord:
    """`ccrp snapshot build`: the golden image from the recipe, recorded for new clones. With
    `if_missing`, the recorded one is kept while its image exists and holds the inventory's
    software."""
    from ..services.workloads import stale_snapshot

    with fleet.store.lock():
        recorded = fleet.store.load_state().snapshot or {}
        current = recorded.get("image")
        # Kept only while it holds the inventory's software (a changed workspace needs a new one).
        if if_missing and current and provider.has_image(current) and bool(recorded.get("bare")) == bare \
                and stale_snapshot(fleet, fleet.store.load_state()) is None:
            kept = [s for s in provider.list_snapshots() if s.id == recorded.get("id") or s.name == current]
            if kept:
                say(f"snapshot {current} exists; new clones start from it")
                return kept[0]
        return _build_retained(fleet, provider, say, bare)


def _build_retained(fleet: Fleet, provider: Provider, say: Progress, bare: bool = False) -> SnapshotRecord:
    """Build the golden image, record it, drop the snapshots retention lets go (under the fleet lock)."""
    record = build(fleet, provider, say, bare=bare)
    retain(fleet, provider, say)
    say(f"snapshot {record.name} recorded: new clones of fleet {fleet.name!r} start from it")
    return record


def ensure_snapshot(fleet: Fleet, provider: Provider, say: Progress, robots: list[str] | None = None) -> None:
    """A new Docker fleet's golden image is built by the first command that creates a clone, as
    `ccrp snapshot build` would (the caller holds the fleet lock). A cloud's is baked on purpose
    (`ccrp snapshot bake`: a builder instance, minutes, billed), so there the clone says so.
    The clones of `robots` (default: every member) are held against the quotas first: a host
    without room for them refuses before minutes of building (and a GB of libvirt pool)."""
    from .quotas import check_growth
    from ..providers import Ability

    recorded = fleet.store.load_state().snapshot or {}
    if Ability.LOCAL_BUILD not in provider.abilities or (recorded.get("image") and provider.has_image(recorded["image"])):
        return
    check_growth(fleet, provider, [r.name for r in fleet.members(fleet.load_allocated())] if robots is None else robots, say)
    say(f"fleet {fleet.name!r} has no snapshot yet: building it (as `ccrp snapshot build`)")
    _build_retained(fleet, provider, say)


def snapshot_bake(fleet: Fleet, provider: Provider, say: Progress, base_image: str | None, timeout: float) -> SnapshotRecord:
    """`ccrp snapshot bake`: a builder instance installs the recipe, is captured, then terminated."""
    with fleet.store.lock():
        record = bake(fleet, provider, say, base_image=base_image, timeout=timeout)
        retain(fleet, provider, say)
    return record


def snapshot_create(fleet: Fleet, provider: Images, robot: str, use: bool) -> SnapshotRecord:
    """`ccrp snapshot create`: capture a configured clone as a snapshot."""
    with fleet.store.lock():
        return create(fleet, provider, robot, use)


def snapshot_delete(fleet: Fleet, provider: Images, snapshot: str, force: bool) -> None:
    """`ccrp snapshot delete`."""
    with fleet.store.lock():
        delete(fleet, provider, snapshot, force)
