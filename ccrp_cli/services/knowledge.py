"""Knowledge sync between clones (docs/services.md, Knowledge sync): each clone's agent config, what
`fleet up` pushes and starts for it, and `ccrp knowledge list|add|remove|sync`.

The agent (agent/knowledge.py as ccrp-knowledge.service, its own user) keeps each dataset the clone
shares under KNOWLEDGE_ROOT/<dataset>/ and talks to its partners over the relay's channel: the
common network, mutual TLS with the clone's relay certificate, partners admitted by the CN of
theirs. Its config is a pushed file (/etc/ccrp/knowledge.json, not secret), re-read when it changes.
Commands reach the agent through the provider's exec (its control socket, root only) and push.
"""

from __future__ import annotations

import base64
import json
import secrets
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..agent.knowledge import name_problem
from ..errors import CcrpError, InputError, shown
from ..fleet import Fleet
from ..models.state import FleetState
from ..render.files import BundleFile
from ..models.layout import CCRP_ETC, CCRP_LIB, KNOWLEDGE_USER, SECRETS_DIR
from .base import Boot, CloneService, ServiceContext

if TYPE_CHECKING:
    from ..models.inventory import Robot
    from ..providers.base import Reaches

UNIT = "ccrp-knowledge.service"
CONFIG = f"{CCRP_ETC}/knowledge.json"
ROOT = "/var/lib/ccrp/knowledge"
RUN = "/run/ccrp-knowledge"
STATUS = f"{RUN}/status.json"
AGENT = f"{CCRP_LIB}/knowledge.py"
# What one `knowledge add` moves per file: it is pushed whole, base64 in memory, through the provider.
MAX_ITEM = 64 << 20


def knowledge_config(fleet: Fleet, state: FleetState, robot: str, live: set[str] | None = None) -> dict | None:
    """/etc/ccrp/knowledge.json of robot's clone; None when it shares no dataset. Its partners are
    the clones that share a dataset with it, are up (`live`, by default those state calls ready)
    and hold a current relay certificate."""
    from .sharing import zenoh_id

    inv = fleet.inventory
    k = inv.services.knowledge
    plan = fleet.plan(state)
    datasets = inv.datasets_of(robot, [m.name for m in fleet.members(state) if m.name in plan])
    if k is None or not datasets or robot not in plan:
        return None
    if live is None:
        live = {n for n, rec in state.robots.items() if rec.phase == "ready"}
    cns = fleet.pki.relay_cns()
    partners = sorted({m for members in datasets.values() for m in members
                       if m != robot and m in live and m in plan and m in cns})
    return {
        "fleet": inv.fleet,
        "robot": robot,
        "id": zenoh_id(inv.fleet, f"{robot}/knowledge"),
        "listen": f"tls/{plan[robot].common_ip}:{k.port}",
        "peers": {p: {"endpoint": f"tls/{plan[p].common_ip}:{k.port}", "id": zenoh_id(inv.fleet, f"{p}/knowledge"),
                      "cn": cns[p]} for p in partners},
        "datasets": datasets,
        "quotas": {ds: {"items": k.datasets[ds].quota.items, "bytes": k.datasets[ds].quota.bytes} for ds in datasets},
        "reconcile": k.reconcile,
        "tls": {"ca": f"{SECRETS_DIR}/relay-ca.crt", "cert": f"{SECRETS_DIR}/relay.crt", "key": f"{SECRETS_DIR}/relay.key"},
        "root": ROOT,
        "status": STATUS,
        "socket": f"{RUN}/ctl.sock",
    }


def knowledge_files(fleet: Fleet, state: FleetState, robot: str, live: set[str] | None = None) -> list[BundleFile]:
    """What `fleet up` pushes to robot's clone: its config, then the agent itself; [] when it shares
    no dataset. The agent (stdlib + the Zenoh the relay's snapshot has) comes with its config, not
    in user-data: a bare cloud image's user-data, which carries the image's agents, would not fit
    AWS's 16 KiB with it (measured: 22.9 KiB gzipped, 15.8 KiB without)."""
    from ..resources import agent_source

    cfg = knowledge_config(fleet, state, robot, live)
    if cfg is None:
        return []
    return [BundleFile("knowledge.json", json.dumps(cfg, indent=1, sort_keys=True) + "\n", 0o644, CONFIG),
            BundleFile("knowledge.py", agent_source("knowledge"), 0o755, AGENT)]


def absent_config() -> BundleFile:
    """Probed on a clone that shares no dataset: if the file is there, it is removed."""
    return BundleFile("knowledge.json", "", 0o644, CONFIG)


OFF_SH = f'rm -f "{CONFIG}" && systemctl stop {UNIT}'


def apply_knowledge(provider: Reaches, robot: str, files: list[BundleFile], have: dict[str, str], restart: bool) -> None:
    """After the config and agent went with the clone's settings: restart the agent where its code
    changed or the relay's TLS files were just pushed (`restart`), start it where only its config
    is new (a running agent re-reads the file), or turn it off where the clone shares no dataset
    any more."""
    from ..probe import same

    if files:
        restart = restart or not same(have, [f for f in files if f.dest == AGENT])
        if not restart and same(have, files):
            return
        rc, out = provider.transport.exec(robot, ["systemctl", "restart" if restart else "start", UNIT], timeout=30)
        if rc != 0:
            raise CcrpError(f"cannot start the knowledge agent on robot {robot!r}'s clone: {out.strip()[-200:]}",
                            hint=f"a clone made before knowledge sync existed has no unit for it: ccrp clone delete -i "
                                 f"INVENTORY --robot {robot}, then ccrp fleet up -i INVENTORY")
    elif CONFIG in have:
        rc, out = provider.transport.exec(robot, ["sh", "-c", OFF_SH], timeout=30)
        if rc != 0:
            raise CcrpError(f"cannot turn knowledge sync off on robot {robot!r}'s clone: {out.strip()[-200:]}")


class Knowledge(CloneService):
    """Its unit is in every clone's user-data; its config and agent go with the clone's settings
    (its partners are the relay's kind: reshared when the fleet changes), and the agent is
    (re)started once the clone serves."""

    name = "knowledge"
    settings = True
    reshared = True
    boot = Boot(units=(UNIT,), users=(KNOWLEDGE_USER,))

    def files(self, ctx: ServiceContext) -> list[BundleFile]:
        return knowledge_files(ctx.fleet, ctx.state, ctx.robot.name, ctx.live)

    def absent(self) -> list[BundleFile]:
        return [absent_config()]

    def apply(self, clone: Reaches, robot: str, files: list[BundleFile], have: dict[str, str],
              pushed_keys: bool) -> list[str]:
        apply_knowledge(clone, robot, files, have, restart=pushed_keys)  # the agent uses the relay's TLS files
        return []

    def status(self, fleet: Fleet, state: FleetState, robot: Robot, health: dict | None) -> dict:
        return {"knowledge": knowledge_row(fleet, state, robot.name, health)}


# -- the commands --------------------------------------------------------------------------------

def _check(fleet: Fleet, robot: str, dataset: str) -> None:
    state = fleet.store.load_state()
    fleet.robot(state, robot)  # one line when the fleet has no such robot
    shared = fleet.inventory.datasets_of(robot, [m.name for m in fleet.members(state)])
    if dataset not in shared:
        have = ", ".join(shared) or "none"
        raise InputError(f"dataset {shown(dataset)} is not shared with robot {robot!r} (its datasets: {have})",
                         hint="services.knowledge.datasets in the inventory names the robots of each dataset")


def _ctl(provider: Reaches, robot: str, request: dict, spool: str | None = None, timeout: float = 120) -> dict:
    argv = ["python3", AGENT, "ctl", json.dumps(request)] + ([spool] if spool else [])
    rc, out = provider.transport.exec(robot, argv, timeout=timeout)
    try:
        reply = json.loads(out.strip().splitlines()[-1])
    except (ValueError, IndexError):
        raise CcrpError(f"robot {robot!r}'s knowledge agent gave no answer: {out.strip()[-200:]}") from None
    if rc == 3:
        raise CcrpError(f"robot {robot!r}'s clone runs no knowledge agent: {reply.get('error')}",
                        hint="ccrp fleet up -i INVENTORY starts it where services.knowledge shares a dataset")
    if not reply.get("ok"):
        raise CcrpError(f"robot {robot!r}'s knowledge agent: {shown(reply.get('error'), 200)}")
    return reply


def list_items(fleet: Fleet, provider: Reaches, robot: str, dataset: str) -> dict:
    _check(fleet, robot, dataset)
    return _ctl(provider, robot, {"op": "list", "dataset": dataset})


def item_name(path: Path) -> str:
    """The file's name as the item's, checked as the agents check it (agent/knowledge.py), so a
    name no clone could store is refused here, before anything is sent."""
    name = path.name
    problem = name_problem(name)
    if problem:
        raise InputError(f"cannot name an item {shown(name)}: {problem}")
    return name


def read_items(paths: list[Path]) -> list[tuple[str, bytes]]:
    """Every file read before anything is sent, so a bad one changes nothing."""
    if not paths:
        raise InputError("knowledge add needs at least one FILE")
    out = []
    for p in paths:
        name = item_name(p)
        try:
            if p.stat().st_size > MAX_ITEM:
                raise InputError(f"{shown(str(p))} is over {MAX_ITEM >> 20} MiB, the most one item may be")
            out.append((name, p.read_bytes()))
        except OSError as exc:
            raise InputError(f"cannot read {shown(str(p))}: {exc.strerror}") from None
    if len({n for n, _ in out}) != len(out):
        raise InputError("two FILEs have the same name")
    return out


def check_quota(fleet: Fleet, dataset: str, robot: str, listed: dict, items: list[tuple[str, bytes]]) -> None:
    """Refuse in one line, before anything is pushed, files that would take the dataset past its
    quota (services.knowledge.datasets.<ds>.quota) on robot's clone, whose `list` is `listed`. The
    agent checks each add too, and a partner's items on their way may still fill it first."""
    import hashlib

    knowledge = fleet.inventory.services.knowledge
    assert knowledge is not None, "add_items checked the dataset is shared (_check)"
    quota = knowledge.datasets[dataset].quota
    have = {(i["name"], i["sha256"]) for i in listed["items"]}
    new = {(n, hashlib.sha256(data).hexdigest()): len(data) for n, data in items}
    new = {k: size for k, size in new.items() if k not in have}
    count, size = len(listed["items"]) + len(new), listed["bytes"] + sum(new.values())
    if count > quota.items or size > quota.bytes:
        raise InputError(f"dataset {dataset!r} on robot {robot!r} would hold {count} items of {size} bytes, over its "
                         f"quota of {quota.items} items and {quota.bytes} bytes; nothing was added",
                         hint=f"ccrp knowledge remove what it no longer needs, or raise "
                              f"services.knowledge.datasets.{dataset}.quota in the inventory")


def add_items(fleet: Fleet, provider: Reaches, robot: str, dataset: str, paths: list[Path]) -> list[dict]:
    """Add files to the dataset on robot's clone; its agent sends them to the partners at once."""
    _check(fleet, robot, dataset)
    items = read_items(paths)
    # Before pushing anything: the agent answers, and the files fit the dataset's quota.
    check_quota(fleet, dataset, robot, _ctl(provider, robot, {"op": "list", "dataset": dataset}), items)
    added = []
    for name, data in items:
        # Root-only, beside the datasets (no dataset name starts with a dot); the ctl client reads
        # and removes it. Not in /run: Docker's put_archive does not reach a container's tmpfs.
        spool = f"{ROOT}/.spool-{secrets.token_hex(8)}.b64"
        provider.transport.push_files(robot, [BundleFile("spool", base64.b64encode(data).decode(), 0o600, spool)], restart=[])
        reply = _ctl(provider, robot, {"op": "add", "dataset": dataset, "name": name}, spool)
        added.append({**reply["item"], "new": reply["new"]})
    return added


def remove_items(fleet: Fleet, provider: Reaches, robot: str, dataset: str, items: list[str]) -> list[dict]:
    """Remove items (by name: every content of that name; or by sha256) everywhere: a tombstone
    goes to the partners."""
    _check(fleet, robot, dataset)
    if not items:
        raise InputError("knowledge remove needs at least one NAME or SHA256")
    out = []
    for item in items:
        reply = _ctl(provider, robot, {"op": "remove", "dataset": dataset, "item": item})
        if not reply["removed"]:
            raise InputError(f"dataset {dataset!r} on robot {robot!r} has no item {shown(item)}",
                             hint=f"ccrp knowledge list -i INVENTORY --robot {robot} --dataset {dataset}")
        out += reply["removed"]
    return out


def sync(fleet: Fleet, provider: Reaches, robot: str, dataset: str) -> dict:
    """Reconcile now: robot's clone pulls its partners' indexes and fetches what it lacks."""
    _check(fleet, robot, dataset)
    return _ctl(provider, robot, {"op": "sync", "dataset": dataset})


# -- merge: one rosbag from a dataset's bags (the thesis's merge_bag) -------------------------------

class _Once:
    """What a merge writes: each message once. One met again (same connection, time and bytes, as
    two clones' copies of one recording are) is counted as a duplicate instead."""

    def __init__(self) -> None:
        self.seen: set[tuple] = set()
        self.count = self.dups = 0

    # rosbags' Writer and connection of either bag format (rosbags.* is not type-checked: pyproject.toml).
    def write(self, writer: Any, conn: Any, key: tuple, t: int, data: bytes) -> None:
        import hashlib

        mark = (key, t, hashlib.sha256(data).digest())
        if mark in self.seen:
            self.dups += 1
            return
        self.seen.add(mark)
        writer.write(conn, t, data)
        self.count += 1


def merge_bag_files(paths: list[Path], out: Path, names: list[str] | None = None) -> dict:
    """Write one ROS 1 bag with every message of `paths` (shown in errors as `names`), in time
    order. Connections are one per (topic, type, md5sum); a message met twice (same connection,
    time and bytes: two clones recorded the same, or a bag merged before) is written once."""
    import heapq
    from contextlib import ExitStack

    from rosbags.rosbag1 import Reader, ReaderError, Writer

    def ident(c: Any) -> tuple[str, str, str]:
        return c.topic, c.msgtype, c.digest

    once = _Once()
    try:
        with ExitStack() as stack:
            readers = []
            for p, name in zip(paths, names or [p.name for p in paths]):
                try:
                    readers.append(stack.enter_context(Reader(p)))
                except Exception as exc:  # noqa: BLE001 - rosbags raises what the bytes make it (ReaderError, UnicodeDecodeError...)
                    raise CcrpError(f"{shown(name)} is not a ROS 1 bag: {type(exc).__name__}: {shown(str(exc), 120)}",
                                    hint="merge takes the dataset's items named *.bag; remove or rename this one") from None
            writer = stack.enter_context(Writer(out))
            conns = {}
            for r in readers:
                for c in r.connections:
                    if ident(c) not in conns:
                        # rosbags 0.11 gives a MessageDefinition (its text in .data), older ones the text.
                        msgdef = getattr(c.msgdef, "data", c.msgdef)
                        conns[ident(c)] = writer.add_connection(c.topic, c.msgtype, msgdef=msgdef, md5sum=c.digest,
                                                                callerid=getattr(c.ext, "callerid", None),
                                                                latching=getattr(c.ext, "latching", None))
            streams = [((t, i, ident(c), data) for c, t, data in r.messages()) for i, r in enumerate(readers)]
            for t, _i, k, data in heapq.merge(*streams, key=lambda m: (m[0], m[1])):
                once.write(writer, conns[k], k, t, data)
    except ReaderError as exc:
        out.unlink(missing_ok=True)
        raise CcrpError(f"cannot read a bag of the dataset: {shown(str(exc), 200)}") from None
    except CcrpError:
        out.unlink(missing_ok=True)
        raise
    return {"bags": len(paths), "messages": once.count, "duplicates": once.dups,
            "topics": sorted({k[0] for k in conns}), "out": str(out)}


def merge_bag2_files(paths: list[Path], out: Path, names: list[str] | None = None) -> dict:
    """Write one ROS 2 bag (a rosbag2 directory `out`, MCAP storage: Jazzy's default) with every
    message of `paths` (rosbag2 storage files, *.mcap or *.db3, each read without its
    metadata.yaml; shown in errors as `names`), in time order. Connections are one per (topic,
    type), with the first bag's serialization format and QoS; a message met twice (same topic,
    type, time and bytes) is written once. Types come from the bags' own definitions."""
    import shutil
    from contextlib import ExitStack

    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.rosbag2 import Reader, Writer
    from rosbags.rosbag2.writer import StoragePlugin
    from rosbags.typesys import Stores, get_typestore

    names = names or [p.name for p in paths]
    for p, name in zip(paths, names):
        try:
            with Reader(p):
                pass
        except Exception as exc:  # noqa: BLE001 - rosbags raises what the bytes make it
            raise CcrpError(f"{shown(name)} is not a ROS 2 bag: {type(exc).__name__}: {shown(str(exc), 120)}",
                            hint="merge takes the dataset's items named *.mcap or *.db3 (rosbag2 storage files); "
                                 "remove or rename this one") from None
    once = _Once()
    conns: dict[tuple[str, str], object] = {}
    try:
        with ExitStack() as stack:
            # Bags without type definitions (a db3 of a distro before Iron) are read as Jazzy's types.
            reader = stack.enter_context(AnyReader(paths, default_typestore=get_typestore(Stores.ROS2_JAZZY)))
            writer = stack.enter_context(Writer(out, version=9, storage_plugin=StoragePlugin.MCAP))
            types = reader.typestore
            for c in reader.connections:
                k = (c.topic, c.msgtype)
                if k not in conns:
                    msgdef = (c.msgdef.data if c.msgdef.format != MessageDefinitionFormat.NONE
                              else types.generate_msgdef(c.msgtype, ros_version=2)[0])
                    conns[k] = writer.add_connection(c.topic, c.msgtype, msgdef=msgdef, rihs01=types.hash_rihs01(c.msgtype),
                                                     serialization_format=c.ext.serialization_format,
                                                     offered_qos_profiles=c.ext.offered_qos_profiles)
            for c, t, data in reader.messages():
                k = (c.topic, c.msgtype)
                once.write(writer, conns[k], k, t, data)
    except Exception as exc:  # noqa: BLE001 - a bag rosbags could open but not read through, or types it cannot join
        shutil.rmtree(out, ignore_errors=True)
        raise CcrpError(f"cannot merge the dataset's ROS 2 bags: {type(exc).__name__}: {shown(str(exc), 200)}") from None
    return {"bags": len(paths), "messages": once.count, "duplicates": once.dups,
            "topics": sorted({k[0] for k in conns}), "out": str(out)}


def bag_suffixes(ros2: bool) -> tuple[str, ...]:
    """The dataset items `merge` takes as bags: ROS 1 bags, or rosbag2 storage files."""
    return (".mcap", ".db3") if ros2 else (".bag",)


def merge(fleet: Fleet, provider: Reaches, robot: str, dataset: str, out: Path) -> dict:
    """The dataset's bags on robot's clone, fetched and merged into `out`: items named *.bag into a
    ROS 1 bag on a ROS 1 fleet, *.mcap and *.db3 into a rosbag2 directory on a ROS 2 one."""
    import hashlib
    import tempfile

    _check(fleet, robot, dataset)
    ros2 = fleet.inventory.ros.ros2
    if out.exists():
        raise InputError(f"{shown(str(out))} exists already",
                         hint="name a new directory with --out" if ros2 else "name a new file with --out")
    try:
        import rosbags  # noqa: F401
    except ImportError:
        raise InputError("ccrp knowledge merge needs the rosbags library", hint="pip install 'ccrp[rosbag]'") from None
    suffixes = bag_suffixes(ros2)
    bags = [i for i in _ctl(provider, robot, {"op": "list", "dataset": dataset})["items"]
            if i["name"].lower().endswith(suffixes)]
    if not bags:
        kinds = " or ".join(f"*{x}" for x in suffixes)
        raise InputError(f"dataset {dataset!r} on robot {robot!r} has no bags (items named {kinds})")
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for k, item in enumerate(bags):
            rc, text = provider.transport.exec(robot, ["base64", "-w0", f"{ROOT}/{dataset}/objects/{item['sha256']}"], timeout=300)
            try:
                data = base64.b64decode(text.strip().splitlines()[-1], validate=True) if rc == 0 else b""
            except (ValueError, IndexError):
                data = b""
            if hashlib.sha256(data).hexdigest() != item["sha256"]:
                raise CcrpError(f"cannot fetch {shown(item['name'])} from robot {robot!r}'s clone (removed meanwhile?)",
                                hint=f"ccrp knowledge list -i INVENTORY --robot {robot} --dataset {dataset}")
            # rosbags tells a storage file's kind by its suffix.
            path = Path(tmp) / f"{k}{Path(item['name']).suffix.lower() if ros2 else '.bag'}"
            path.write_bytes(data)
            paths.append(path)
        names = [i["name"] for i in bags]
        return merge_bag2_files(paths, out, names) if ros2 else merge_bag_files(paths, out, names)


def knowledge_row(fleet: Fleet, state: FleetState, robot: str, health: dict | None) -> dict | None:
    """`ccrp status`'s view of robot's knowledge agent: None when its clone shares no dataset;
    `running` only while the agent reports (a status file under 10 s old, agent/health.py)."""
    cfg = knowledge_config(fleet, state, robot)
    if cfg is None:
        return None
    h = (health or {}).get("knowledge") or {}
    running = bool(h.get("running"))
    seen = h.get("peers", {}) if running else {}
    return {"running": running, "datasets": h.get("datasets", {}) if running else {},
            "peers": {p: bool(seen.get(p)) for p in cfg["peers"]}, "errors": h.get("errors", 0),
            "last_error": h.get("last_error"), "last_reconcile": h.get("last_reconcile")}
