"""The protocols every backend implements (in the spirit of SkyPilot's sky/provision) and what it declares."""

from __future__ import annotations

import gzip
import json
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING, Any, Callable, Iterable, Literal, Protocol, Sequence

from pydantic import BaseModel

from ..errors import CcrpError
from ..models.layout import AUTOSTOP_BOOT_LINE, AUTOSTOP_MARK

if TYPE_CHECKING:
    from ..recipes import Platform

# Labels / tags on every resource ccrp creates; list, delete and gc filter on them.
LABEL_MANAGED = "ccrp-managed"
LABEL_FLEET = "ccrp-fleet"
LABEL_ROBOT = "ccrp-robot"
LABEL_ROLE = "ccrp-role"  # clone | builder | robot-sim | power-sim | snapshot | network | secrets


def owner_labels(fleet: str, role: str, robot: str | None = None) -> dict[str, str]:
    labels = {LABEL_MANAGED: "true", LABEL_FLEET: fleet, LABEL_ROLE: role}
    if robot:
        labels[LABEL_ROBOT] = robot
    return labels


RESULT_JSON = "/run/cloud-init/result.json"
# Until $0 (cloud-init's result) exists or systemd says the boot is over (cloud-final is part of
# it), then print it. systemctl every second, the file test every 0.2 s.
WAIT_RESULT_SH = """i=0
until [ -e "$0" ]; do
  if [ $((i % 5)) -eq 4 ]; then
    case $(systemctl is-system-running 2>/dev/null) in running|degraded|maintenance|stopping) break ;; esac
  fi
  i=$((i + 1)); sleep 0.2
done
cat "$0" 2>/dev/null"""


def wait_cloud_init(robot: str, run: Callable[[list[str]], tuple[int, str]], timeout: float) -> None:
    """Until cloud-init has finished on a clone, `run` executing a command there as root (any
    transport, within what is left of `timeout`). A shell loop waits for this boot's result.json
    (/run is a tmpfs) or for the boot to be over without one: `cloud-init status --wait` is a Python
    program polling the whole boot long (0.3 CPU-s per clone on Docker, a Python start of 8-10 s and
    more under TCG, measured). Anything but a clean result gets cloud-init's own answer."""
    rc, out = run(["sh", "-c", WAIT_RESULT_SH, RESULT_JSON])
    if rc == 0 and cloud_init_clean(out):
        return
    rc, out = run(["cloud-init", "status", "--wait", "--long"])
    check_cloud_init(robot, rc, out, timeout)


def check_cloud_init(robot: str, rc: int, out: str, timeout: float) -> None:
    """Judge `cloud-init status --wait --long` run on a clone (any transport): a one-line error
    with cloud-init's own detail unless it finished."""
    if rc == 124:
        raise CcrpError(f"clone cri-{robot}: cloud-init did not finish within {timeout:.0f} s")
    if rc not in (0, 2):  # 2: finished with recoverable errors (cloud-init >= 23.4)
        detail = " ".join(line.strip() for line in out.splitlines() if line.strip().startswith(("status", "detail", "(")))
        raise CcrpError(f"clone cri-{robot}: cloud-init failed: {detail[:300] or out.strip()[-300:]}",
                        hint=f"ccrp clone exec --robot {robot} -- cloud-init status --long")


def autostop_note(text: str) -> str | None:
    """The last line the clone's autostop agent wrote (agent/autostop.py), without its mark; None
    when that is the line it writes at start (the clone stopped otherwise during that boot)."""
    lines = [line.split(AUTOSTOP_MARK, 1)[1].strip() for line in text.splitlines() if AUTOSTOP_MARK in line]
    return lines[-1] if lines and lines[-1] != AUTOSTOP_BOOT_LINE else None


def cloud_init_clean(result_json: str) -> bool:
    """cloud-init's /run/cloud-init/result.json (written when its last stage ends) says it finished
    with no errors."""
    try:
        return json.loads(result_json)["v1"]["errors"] == []
    except (ValueError, KeyError, TypeError):
        return False


# The robot label of the fleet's entry gateway (ops/gateway.py), the instance of role "gateway": the
# hyphen keeps it out of robot names' alphabet. The transport reaches it by this name.
GATEWAY = "entry-gateway"
GATEWAY_ROLE = "gateway"


class CloneSpec(BaseModel):
    """What to create for one robot."""

    robot: str
    hostname: str
    image: str
    user_data: str
    instance_id: str
    common_ip: str
    # The clone's VPN subnet (addressing plan): clouds route it to the instance so clones reach
    # each other's robots.
    vpn_subnet: str | None = None
    # Goes into the ccrp-role label: "clone", or "builder" for the instance `snapshot bake` boots
    # (query() lists clones only; terminate/console_output/create_snapshot find it by robot label).
    role: str = "clone"


class CloneState(str, Enum):
    """A clone's lifecycle in ccrp's words; each provider maps its own (ACTIVE, RUNNING, exited...)."""

    PENDING = "pending"  # being created, booting, rebooting
    RUNNING = "running"
    STOPPING = "stopping"
    STOPPED = "stopped"  # exists, can be started again
    DELETING = "deleting"  # on its way out: never reused
    ERROR = "error"
    UNKNOWN = "unknown"  # a word this version of ccrp does not know

    @classmethod
    def of(cls, word: str, table: dict[str, "CloneState"]) -> "CloneState":
        return table.get(word, cls.UNKNOWN)


class Origin(str, Enum):
    """What run_instance did to have the robot's clone: each provider says it, so the core never
    asks the provider again to tell a started clone from one that was running."""

    CREATED = "created"  # none existed: this call made it (a failed create rolls back only these)
    RESUMED = "resumed"  # it existed stopped: this call started it (it boots again)
    REUSED = "reused"  # it existed running, or on its way there: left as it was


class CloneRecord(BaseModel):
    """What exists for one robot, as the provider sees it."""

    robot: str
    provider_id: str
    state: CloneState
    status: str  # the provider's own word, kept for messages (running, exited, ACTIVE...)
    public_ip: str | None = None
    common_ip: str | None = None
    origin: Origin | None = None  # set by run_instance; None on what query() lists
    # HOST:PORT robots dial when it is not public_ip at the VPN port (a port the libvirt host
    # forwards to the clone's, for robots outside it).
    endpoint: str | None = None

    @property
    def created(self) -> bool:
        return self.origin is Origin.CREATED


class SnapshotRecord(BaseModel):
    id: str
    name: str
    created: str
    source: str  # "build" or the robot whose clone was captured
    size_mb: float | None = None


class Role(str, Enum):
    """What an owned resource is to the fleet, in ccrp's words: `ccrp gc` judges a resource by its
    role; its kind is the backend's own word (instance, vpc, port_forward...)."""

    BOOTSTRAP = "bootstrap"  # one per fleet, made or reused by bootstrap (networks, firewalls, key pair)
    CLONE = "clone"  # a robot's clone (an instance, a container)
    IMAGE = "image"  # a snapshot image (the fleet's, or a cache no state records)
    ROBOT_SIDE = "robot-side"  # started by hand for a robot (`ccrp robot sim`), not recorded as a clone
    PER_ROBOT = "per-robot"  # what belongs to one robot's clone (its public IP, volumes, routes)
    GATEWAY = "gateway"  # the fleet's entry gateway: its instance, port and the fleet's public address


class OwnedResource(BaseModel):
    """Anything in the cloud carrying the fleet's ownership labels (what `ccrp gc` looks at)."""

    kind: str  # the backend's own word, for messages and its delete_owned
    id: str
    name: str = ""
    robot: str | None = None
    # Set by the backend where it lists what it owns (with_roles): gc reads nothing else.
    role: Role = Role.PER_ROBOT


def with_roles(found: Iterable[OwnedResource], roles: dict[str, Role]) -> list[OwnedResource]:
    """`found` with each resource's role, from the backend's own table kind -> role (a kind it does
    not name belongs to a robot); what carries the gateway's robot label is the gateway's."""
    return [r.model_copy(update={"role": Role.GATEWAY if r.robot == GATEWAY else roles.get(r.kind, Role.PER_ROBOT)})
            for r in found]


class Quota(BaseModel):
    """One quota that new clones draw on, in the cloud's own numbers (Provider.quotas). The core
    (ccrp_cli/ops/quotas.py) holds what a command will create against it before it creates anything;
    `fleet plan` and `ccrp doctor` show it."""

    name: str  # the cloud's own name for it: STATIC_ADDRESSES, cores, EC2-VPC Elastic IPs...
    scope: str  # where it counts, for messages: "region europe-west1", "project of cloud 'lab'"
    limit: float
    used: float  # in use now, by this fleet and by anything else under the same quota
    per_clone: float  # what one new clone of the fleet's default size takes
    # Robots (of those asked about) whose new clone takes another amount than per_clone: a
    # robot's own instance_type, or the public address it holds already from an earlier attempt (0).
    per_robot: dict[str, float] = {}
    hint: str = ""  # where this quota is raised, when the cloud names a place
    # What the fleet takes once, however many clones it creates: its entry gateway's instance and
    # public address while it has none (provider.entry: gateway).
    once: float = 0.0

    @property
    def free(self) -> float:
        return max(self.limit - self.used, 0.0)

    def need(self, robots: Iterable[str]) -> float:
        """What creating the clones of `robots` takes of this quota."""
        robots = list(robots)
        return float(sum(self.per_robot.get(r, self.per_clone) for r in robots)) + (self.once if robots else 0.0)


class Ability(str, Enum):
    """What a backend can do beyond the common lifecycle; commands check these up front."""

    LOCAL_BUILD = "snapshot build"  # build the golden image on this host (Docker)
    BAKE = "snapshot bake"  # a builder instance in the cloud installs the recipe and is captured
    # Simulated robots (containers of this host) sit on the fleet's own public network, a network
    # or bridge of this host (Docker, libvirt); a cloud fleet's dial their clone from anywhere.
    ROBOT_ATTACH = "robot sim on the fleet's own network"
    # Its snapshot images live on this host, where they outlive the state that recorded them (Docker).
    HOST_IMAGES = "snapshot images on this host"
    # One instance holds the fleet's one public address and forwards each robot's port to its clone
    # (render/gateway.py); the clones have no public address (provider.entry: gateway).
    ENTRY_GATEWAY = "entry gateway"


@dataclass(frozen=True)
class InitSection:
    """What `ccrp init --provider <kind>` writes for a backend (ProviderInfo.init): its `provider:`
    section, and what the rest of the first inventory needs to know of it."""

    # The section's lines under `provider:`, a str.format template: {public} is a free pool of this
    # host when public_pool asks for one (a literal brace is doubled).
    lines: str
    # The backend makes a network of this host (provider.public_cidr): init picks a pool free here.
    public_pool: bool = False
    # Autostop on in the first inventory: an idle clone costs money (not a container of this host).
    autostop: bool = True
    # What `ccrp init` writes with no --provider (one backend says so).
    default: bool = False
    # `ccrp init --cloud NAME`: "module:function" (as ProviderInfo.factory) that asks the cloud for the
    # values of `lines`' other fields; `values` are those fields' defaults, written without --cloud.
    discover: str | None = None
    values: tuple[tuple[str, str], ...] = ()


@dataclass(frozen=True)
class ProviderInfo:
    """What a backend declares about itself without importing its SDK; the registry in
    providers/registry.py collects one per package."""

    kind: str
    settings: type[BaseModel]  # the inventory's `provider:` section for this backend
    # "module:Class", imported when the provider is made: ".docker.provider:DockerProvider" is relative
    # to ccrp_cli.providers; a backend outside ccrp_cli names its module in full.
    factory: str
    abilities: frozenset[Ability]
    user_data_limit: int  # raw bytes the cloud accepts
    user_data_gzip: bool  # whether cloud-init's gzip payload is accepted
    sdk_modules: tuple[tuple[str, str], ...]  # (import name, pip extra) `ccrp doctor` checks
    platform: str = "debian-bookworm"  # the snapshot recipe's platform its clones run (snapshots/*.yaml)
    # Where a clone keeps the secrets ccrp pushes: "memory" (a tmpfs, gone at reboot: the user-data
    # makes it at every boot) or "volume" (a Docker volume the container keeps).
    secrets: Literal["memory", "volume"] = "memory"
    # What run_instance is given for a captured snapshot: GCE boots from an image's name, the
    # others from its id (Glance names need not be unique).
    image_ref: Literal["id", "name"] = "id"
    # Whether create_snapshot captures a running clone; libvirt copies a stopped clone's disk and
    # refuses a running one in one line (QEMU holds the disk's write lock).
    snapshots_running: bool = True
    # Whether a clone runs its own kernel (a VM) or shares the host's (a container): only the former
    # can take kernel settings from its user-data (sysctls such as ROS 2's receive buffers).
    own_kernel: bool = True
    # Host tools `ccrp doctor` looks for: (tool, what it is for), a warning when missing.
    host_tools: tuple[tuple[str, str], ...] = ()
    # Where the backend's quotas are raised, when a quota names no place of its own.
    quota_hint: str = "raise it"
    # Ability.BAKE: the stock Debian 12 cloud image a builder starts from (the recipes'
    # debian-bookworm platform) when neither --base-image nor provider.image names one, and what to
    # do when the cloud does not have it.
    bake_base: str = ""
    bake_base_hint: str = ""
    # `ccrp init --provider <kind>`: None for a backend init does not offer.
    init: InitSection | None = None
    # `ccrp init`'s scan of this host, whatever backend the new inventory names: "module:function"
    # (as factory) returning the ranges this backend has taken here, range -> what it is (Docker's
    # networks, libvirt's); a new fleet's pools avoid them. None: it takes none of this host's.
    host_networks: str | None = None
    # `ccrp doctor`'s row for reaching the backend ("<kind> client" unless it names its own), and
    # whether that answer is the credential (Docker: the engine answering), or the account is
    # checked apart (check_credentials: the clouds').
    reach: str = "client"
    reach_is_credential: bool = False

    def fit_user_data(self, text: str) -> tuple[bytes, bool]:
        """The user-data payload to send and whether it is gzipped, checked before any API call; an
        error when it cannot fit this backend's limit."""
        raw = text.encode()
        if len(raw) <= self.user_data_limit:
            return raw, False
        if self.user_data_gzip:
            packed = gzip.compress(raw, mtime=0)
            if len(packed) <= self.user_data_limit:
                return packed, True
        raise CcrpError(
            f"cloud-init user-data is {len(raw)} bytes, over {self.kind}'s limit of {self.user_data_limit} bytes"
            + (" even gzipped" if self.user_data_gzip else ""),
            hint="share fewer topics per robot or move large files into the snapshot",
        )


class Transport(Protocol):
    """How the core reaches into a clone: Docker execs in the container, the clouds and libvirt log in
    over SSH with pinned host keys (cloud.py SshClones). Commands run as root."""

    # (exit status, stdout and stderr); output past transport.EXEC_OUTPUT_MAX fails the command (CcrpError).
    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]: ...
    # Each file (render/files.py BundleFile) to its `dest` with its mode and group, then the units restarted.
    def push_files(self, robot: str, files: Sequence, restart: Sequence[str] = ()) -> None: ...


class Reaches(Protocol):
    """What code that only runs commands on clones, or pushes files to them, takes of a provider."""

    @property
    def transport(self) -> Transport: ...

    def timeout_scale(self, robot: str) -> int:
        """How many times longer than usual a command on this robot's clone may take (a VM whose CPU
        is emulated: libvirt without KVM); 1 elsewhere."""
        ...


class Lifecycle(Reaches, Protocol):
    """A clone's life: made (or started, or reused), waited for, listed, stopped, deleted; and the
    fleet's shared resources made and removed."""

    kind: str
    abilities: frozenset[Ability]
    max_parallel: int  # clones `fleet up` creates at once

    def bootstrap(self) -> None: ...
    # Create the robot's clone, or start or reuse the one it has; the record's origin says which.
    def run_instance(self, spec: CloneSpec) -> CloneRecord: ...
    def wait_ready(self, robot: str, timeout: float) -> None: ...
    def query(self) -> dict[str, CloneRecord]: ...
    def terminate(self, robot: str) -> bool: ...
    # Ask the robot's running clone to stop (its disk stays); False when none was running. The
    # caller waits for query() to say STOPPED.
    def stop_instance(self, robot: str) -> bool: ...
    def teardown(self) -> list[str]: ...
    def close(self) -> None: ...


class Images(Protocol):
    """Snapshots (golden images and captured clones) and the images clones boot from."""

    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord: ...
    def list_snapshots(self) -> list[SnapshotRecord]: ...
    def delete_snapshot(self, snapshot_id: str) -> None: ...
    def has_image(self, image: str) -> bool: ...
    # The image a name stands for where a cloud names images indirectly (AWS: an SSM parameter).
    def resolve_image(self, image: str) -> str: ...


class Housekeeping(Protocol):
    """What gc, doctor, status and the quota check ask a backend beside the lifecycle."""

    # Why a stopped clone stopped, if its autostop agent stopped it: the agent's line, else None.
    def stop_note(self, robot: str) -> str | None: ...
    # Every resource carrying this fleet's labels, and deleting one of them (gc of leaks).
    def list_owned(self) -> list[OwnedResource]: ...
    def delete_owned(self, resource: OwnedResource) -> None: ...
    # What `fleet down` should have removed and did not ("kind name" each).
    def leftovers(self) -> list[str]: ...
    # Public keys for the clone's login user; None where the transport needs no login (Docker API).
    def login_keys(self) -> list[str] | None: ...
    def check_credentials(self) -> str: ...
    # The quotas new clones draw on, with what creating the clones of `robots` takes of each;
    # [] where the backend has no quota to check (Docker). ccrp_cli/ops/quotas.py decides.
    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]: ...


class Provider(Lifecycle, Images, Housekeeping, Protocol):
    """Every backend implements all three; a function of the core takes the narrowest it uses."""


@dataclass(frozen=True)
class RobotAttachment:
    """Where a simulated robot of the fleet sits (RobotAttach.attach_robot). Its container, on this
    host's Docker engine (RobotHost), joins `network`; `attach(pid)`, if given, wires the
    container's network namespace as soon as it runs, before its VPN first dials."""

    network: str  # a Docker network of this host; "none" when `attach` gives the robot its only interface
    name: str = ""  # the network as `robot sim` reports it, when not `network` (libvirt's NAT network)
    address: str | None = None  # the robot's own address there, when the backend picks it
    attach: Callable[[int], None] | None = None
    # The robot runs the fleet's snapshot (a Docker image of this host, as the clones do) rather
    # than the simulated robots' own image (RobotHost.robot_image).
    clone_image: bool = False

    def __str__(self) -> str:
        return (self.name or self.network) + (f" ({self.address})" if self.address else "")


class Gateways(Protocol):
    """Ability.ENTRY_GATEWAY: the fleet's one gateway instance. run_instance makes it from a spec of
    role "gateway" (robot GATEWAY, its fixed common address) with the fleet's public address, kept
    apart from the instance so a gateway made again has the same; clones then get none, and the
    transport reaches them through the gateway."""

    # The gateway as the cloud sees it (its public_ip the fleet's address); None when there is none.
    def gateway(self) -> CloneRecord | None: ...


class RobotAttach(Protocol):
    """What a provider with Ability.ROBOT_ATTACH adds: where the simulated robot of slot `index` sits
    on the fleet's own public network (Docker: the fleet's <fleet>-public network; libvirt: a veth on
    its NAT bridge, libvirt/robots.py), and detach_robot, which removes what is left of that once
    the robot's container is gone."""

    def attach_robot(self, robot: str, index: int) -> RobotAttachment: ...

    def detach_robot(self, robot: str) -> None: ...


class RobotHost(Protocol):
    """Where a fleet's simulated robots and their power devices run, whatever its backend: systemd
    containers of this host's Docker engine (providers.robot_host). `role` is "robot-sim" or
    "power-sim" (the robot's power device)."""

    def running(self, robot: str) -> bool: ...
    # The fleet's simulated robots here (any state; with `running`, those that run), sorted.
    def names(self, running: bool = False) -> list[str]: ...
    def exec(self, robot: str, argv: list[str], timeout: float = 60, role: str = "robot-sim") -> tuple[int, str]: ...
    def push_files(self, robot: str, files: Sequence, restart: Sequence[str] = (), role: str = "robot-sim") -> None: ...
    # The simulated robots' own image for `distro`, built here once.
    def robot_image(self, distro: str, progress: Callable[[str], None]) -> str: ...
    # (Re)create the robot from `image` where `attachment` says, install `bundle`, run `demo_node`
    # with `python`; its container id.
    def start(self, robot: str, image: str, bundle: Sequence, demo_node: str, attachment: RobotAttachment,
              python: str) -> str: ...
    def stop(self, robot: str) -> bool: ...
    def start_device(self, robot: str, bundle: Sequence) -> str: ...
    def close(self) -> None: ...


@dataclass(frozen=True)
class ImageOutcome:
    """One snapshot image of this host as `ccrp gc` judged it (HostImages.sweep_images)."""

    resource: OwnedResource
    action: str  # orphan | unlabelled (listed, not removed) | kept | deleted | failed
    detail: str


@dataclass(frozen=True)
class Finding:
    """One row of `ccrp doctor` a backend reports about itself."""

    check: str
    status: Literal["ok", "warn", "fail", "skip"]
    detail: str
    hint: str = ""


class HostImages(Protocol):
    """What a provider with Ability.HOST_IMAGES adds: its snapshot images live on this host, where
    they outlive the state directory that recorded them (a temporary CCRP_HOME, a test run), which
    no fleet's gc would see again. `ccrp gc` sweeps the host's orphans (and, when asked, the
    images from before ccrp labelled them: `unlabelled`); `ccrp doctor` reports their disk."""

    def sweep_images(self, dry_run: bool, unlabelled: bool,
                     progress: Callable[[str], None]) -> list[ImageOutcome]: ...

    def images_finding(self) -> Finding: ...


class ImageSoftware(Protocol):
    """The fleet's own software as a LocalBuild puts it in the image (services/workloads.py
    SnapshotSoftware, which the core reads and checks; templates/docker/software.j2)."""

    @property
    def digest(self) -> str: ...
    @property
    def empty(self) -> bool: ...
    @property
    def apt(self) -> list[str]: ...
    @property
    def pip_install(self) -> list[str]: ...
    @property
    def build_type(self) -> str | None: ...
    @property
    def workspace(self) -> Sequence[tuple[str, bytes]]: ...  # (path in the workspace, content)
    @property
    def python_dirs(self) -> list[str]: ...  # the ament_python packages' directories
    @property
    def interface_words(self) -> list[str]: ...  # the interface packages, NAME=DIR, in build order
    @property
    def build_tools(self) -> ImageBuildTools: ...


class ImageBuildTools(Protocol):
    """What building the workspace needs beside its packages' own (the recipe's build_tools)."""

    @property
    def apt(self) -> list[str]: ...
    @property
    def pip(self) -> list[str]: ...


class LocalBuild(Protocol):
    """What a provider with Ability.LOCAL_BUILD adds: `snapshot build` makes the golden image on this
    machine (Docker: the clone image; libvirt: the golden volume made from it): the recipe's
    platform `plat`, ccrp's `agents` (agent/<name>.py, in /usr/local/lib/ccrp of a ROS 1 image: what
    the core's services declare, ops/snapshots.py), the fleet's `software` (None: none) whose digest
    labels it, or a `bare` image."""

    def build_snapshot(self, repo: str, distro: str, plat: Platform, agents: tuple[str, ...],
                       software: ImageSoftware | None, digest: str, bare: bool,
                       progress: Callable[[str], None]) -> SnapshotRecord: ...


class Bake(Protocol):
    """What a provider with Ability.BAKE adds: `snapshot bake` boots a builder instance (run_instance
    with role "builder", which query() does not list), reads its console and reaches it by name."""

    def console_output(self, robot: str) -> str: ...
    # Open the transport to the builder from the record run_instance returned (its host keys
    # pinned from its console, as a clone's); transport.exec and push_files then reach it.
    def connect(self, robot: str, rec: CloneRecord, timeout: float = 300) -> None: ...


class BackendImages(Protocol):
    """A backend's images.py: its snapshots, as functions of its client."""

    def create_snapshot(self, c: Any, robot: str, name: str) -> SnapshotRecord: ...
    def list_snapshots(self, c: Any) -> list[SnapshotRecord]: ...
    def delete_snapshot(self, c: Any, snapshot_id: str) -> None: ...
    def has_image(self, c: Any, image: str) -> bool: ...


class BackendOwned(Protocol):
    """A backend's owned.py: everything of the fleet in the backend, as functions of its client."""

    def list_owned(self, c: Any) -> list[OwnedResource]: ...
    def delete_owned(self, c: Any, resource: OwnedResource) -> None: ...
    def teardown(self, c: Any) -> list[str]: ...
    def leftovers(self, c: Any) -> list[str]: ...


class Composed:
    """A provider in the backends' one shape (docs/architecture.md, "The shape of a backend"): its
    client, and the modules taking it. The snapshot and owned-resource calls of Provider hand the
    client to the backend's images.py and owned.py, which a provider names in one line
    (`images, owned = images, owned`); mypy checks those modules against BackendImages and
    BackendOwned."""

    client: Any
    images: BackendImages
    owned: BackendOwned

    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        return self.images.create_snapshot(self.client, robot, name)

    def list_snapshots(self) -> list[SnapshotRecord]:
        return self.images.list_snapshots(self.client)

    def delete_snapshot(self, snapshot_id: str) -> None:
        self.images.delete_snapshot(self.client, snapshot_id)

    def has_image(self, image: str) -> bool:
        return self.images.has_image(self.client, image)

    def list_owned(self) -> list[OwnedResource]:
        return self.owned.list_owned(self.client)

    def delete_owned(self, resource: OwnedResource) -> None:
        self.owned.delete_owned(self.client, resource)

    def teardown(self) -> list[str]:
        return self.owned.teardown(self.client)

    def leftovers(self) -> list[str]:
        return self.owned.leftovers(self.client)
