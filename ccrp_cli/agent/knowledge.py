#!/usr/bin/python3
"""ccrp knowledge agent: runs ON a clone (system python3 + zenoh, nothing from ccrp; zenoh only for
the agent itself, so `ctl` runs on any python3).

A dataset is a set of items under ROOT/<dataset>/: objects/<sha256> (the content, by its hash),
index.json (one record per (name, sha256): origin, first and last add, last delete) and files/ (a
hard link per live item, under its name; names that several contents share get
<stem>.<origin>-<sha8><suffix> each, so both stay). The index is a join semilattice (earliest
(added, origin), latest add, latest delete), so merging in any order, any number of times, ends
the same on every clone: a union without duplicates, deletions carried as tombstones.

Between clones (Zenoh over the relay's mutual TLS, peers and their certificate CNs from the config):
  ccrp/<fleet>/knowledge/<ds>/<robot>/event      records a clone just changed (put)
  ccrp/<fleet>/knowledge/<ds>/<robot>/index      queryable: that clone's whole index
  ccrp/<fleet>/knowledge/<ds>/<robot>/blob/<sha> queryable: one object's bytes
Each clone writes (puts, replies, declares queryables) under its own <ds>/<robot>/ only: every
receiver's Zenoh access control admits a partner's writes there alone, by the CN of its relay
certificate (`acl`), so the robot a key names is the clone that wrote it. A record that makes an
item live is merged only once its object is here: fetched to tmp/, its size and hash checked,
then renamed into objects/ (a transfer cut anywhere leaves no item), and only within the
dataset's quota. Every `reconcile` seconds, when a peer (re)connects and on `sync`, the agent
pulls every peer's index.

Local control (root only, the socket is the agent user's 0600): `knowledge.py ctl REQUEST [FILE]`.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import os
import queue
import re
import secrets
import socket
import stat
import sys
import threading
import time

DEFAULT_CONFIG = "/etc/ccrp/knowledge.json"
SOCKET = "/run/ccrp-knowledge/ctl.sock"
NOBODY = "no partner (ccrp)"
NAME_CHARS = re.compile(r"[^/\x00-\x1f\x7f]+")
SHA_RE = re.compile(r"^[0-9a-f]{64}$")
ROBOT_RE = re.compile(r"^[a-z][a-z0-9-]{0,62}$")
FETCH_TIMEOUT = 30.0
MAX_ITEM = 1 << 30
# An item's name is a file name in files/, and on a conflict gets `.<origin>-<sha8>` added: the
# file system takes 255 bytes (not characters), so a name keeps room for the longest such suffix
# (an origin of 63 characters, ROBOT_RE): a longer name would fail on the disk of every clone that
# shares the dataset, at every start of their agents.
NAME_BYTES = 255 - len(".-") - 63 - 8  # 182
# Times decide which of an add and a delete wins, and a new add wins by being 1 ms later: a delete
# at NaN, infinity or 1e16 (where 1e16 + 1e-3 == 1e16) would win for ever. A peer's time may be at
# most FUTURE_S ahead of this clock (chrony keeps clones far closer). The index read at start, whose
# records passed that check when they came, only has to be below MAX_TIME (2100): this clock may
# have gone back since, and a record dropped there would take its content along.
FUTURE_S = 600.0
MAX_TIME = 4102444800.0
# What a dataset may hold on this clone when the config names no quota (ccrp's own configs always
# do: services.knowledge.datasets.<ds>.quota, whose default this is): live items, and their bytes.
DEFAULT_QUOTA = {"items": 10000, "bytes": 1 << 30}
# Tombstones are kept (none is collected yet), so the index, in memory and in index.json, is bounded
# apart: at most this many records, live or deleted, per item of the quota.
RECORDS_PER_ITEM = 4
# A peer's records that are refused are reported once each (they come again at every
# reconciliation), remembering at most this many.
REPORTED = 10000


def name_problem(name: object) -> str | None:
    """Why `name` cannot be an item's name, or None when it can (the CLI, the control socket and
    peers' records all ask this)."""
    if not isinstance(name, str) or not name:
        return "an item needs a name"
    if name in (".", "..") or not NAME_CHARS.fullmatch(name):
        return "a file name without '/' or control characters"
    try:
        size = len(name.encode("utf-8"))
    except UnicodeEncodeError:  # a lone surrogate: from a file name that is not UTF-8
        return "a name in UTF-8"
    if size > NAME_BYTES:
        return f"{size} bytes in UTF-8, over the {NAME_BYTES} an item name may have (a conflict adds .<origin>-<sha8>)"
    return None


def log(msg: str) -> None:
    print(f"ccrp-knowledge: {msg}", file=sys.stderr, flush=True)


# -- the merge (pure; unit-tested without Zenoh) -------------------------------------------------

def key(rec: dict) -> tuple[str, str]:
    return rec["name"], rec["sha256"]


def live(rec: dict) -> bool:
    return rec["deleted"] is None or rec["last"] > rec["deleted"]


def valid(rec: object, latest: float = MAX_TIME) -> bool:
    """A record as a peer may send it: names that are safe as file names, hashes, and numbers that
    are numbers (not bools, finite, not negative), times not after `latest`."""
    def when(t: object) -> bool:
        return isinstance(t, (int, float)) and not isinstance(t, bool) and 0 <= t <= latest  # NaN fails

    try:
        return (isinstance(rec, dict) and set(rec) == {"name", "sha256", "size", "origin", "added", "last", "deleted"}
                and name_problem(rec["name"]) is None
                and isinstance(rec["sha256"], str) and bool(SHA_RE.match(rec["sha256"]))
                and type(rec["size"]) is int and 0 <= rec["size"] <= MAX_ITEM  # an int, not a bool
                and isinstance(rec["origin"], str) and bool(ROBOT_RE.match(rec["origin"]))
                and when(rec["added"]) and when(rec["last"]) and (rec["deleted"] is None or when(rec["deleted"])))
    except (TypeError, KeyError):
        return False


def merge(a: dict | None, b: dict) -> dict:
    """The join of two records of one (name, sha256): the first add names the origin, the latest
    add and the latest delete decide whether the item is live."""
    if a is None:
        return dict(b)
    added, origin = min((a["added"], a["origin"]), (b["added"], b["origin"]))
    dels = [d for d in (a["deleted"], b["deleted"]) if d is not None]
    return {"name": a["name"], "sha256": a["sha256"], "size": a["size"], "origin": origin, "added": added,
            "last": max(a["last"], b["last"]), "deleted": max(dels) if dels else None}


def vouched(old: dict | None, rec: dict, sender: str) -> bool:
    """Whether `sender` (the robot its key names, which the ACL binds to the CN of its relay
    certificate) may tell this clone `rec`: an add of its own (origin is the sender), or news of an
    item this clone knows already that leaves its first add (time and origin) as it is: a delete or
    an add again, passed on. Anything else would let one partner say another added something."""
    return rec["origin"] == sender or (old is not None and (old["added"], old["origin"]) <= (rec["added"], rec["origin"]))


def quota_problem(old: dict | None, rec: dict, used: dict, quota: dict) -> str | None:
    """Why merging `rec` (whose index record here is `old`) would take a dataset past its quota,
    given what it `used` ({items, bytes, records}); None when it fits. Only a record that makes an
    item live, or a new record, costs: a delete never is refused."""
    if old is None and used["records"] >= quota["items"] * RECORDS_PER_ITEM:
        return (f"its index holds {used['records']} records (deleted items too), the most for a quota of "
                f"{quota['items']} items")
    if live(merge(old, rec)) and not (old is not None and live(old)):
        if used["items"] >= quota["items"]:
            return f"it holds {used['items']} items, its quota"
        if used["bytes"] + rec["size"] > quota["bytes"]:
            return f"{rec['size']} bytes more than its {used['bytes']} would pass its quota of {quota['bytes']}"
    return None


def account(used: dict, old: dict | None, new: dict) -> None:
    """`used` after `old` became `new` in the index."""
    used["records"] += old is None
    was = old is not None and live(old)
    if live(new) != was:
        sign = 1 if live(new) else -1
        used["items"] += sign
        used["bytes"] += sign * new["size"]


def added(index: dict, name: str, sha: str, size: int, origin: str, now: float) -> dict:
    """The record after adding (name, sha) here: new, or live again after a delete (the add wins
    over a delete it saw, whatever the clocks say)."""
    rec = index.get((name, sha))
    if rec is None:
        return {"name": name, "sha256": sha, "size": size, "origin": origin, "added": now, "last": now, "deleted": None}
    if live(rec):
        return rec
    return {**rec, "last": max(now, rec["deleted"] + 1e-3)}


def removed(rec: dict, now: float) -> dict:
    """The record after a delete here: it wins over every add this clone has seen."""
    return {**rec, "deleted": max(now, rec["last"] + 1e-3)}


def view_names(records) -> dict[str, str]:
    """files/ name -> sha256 of the live items: its own name when no other content has it, else
    <stem>.<origin>-<sha8><suffix> for each, so both versions stay and say where they came from."""
    by_name: dict[str, list[dict]] = {}
    for r in records:
        if live(r):
            by_name.setdefault(r["name"], []).append(r)
    out: dict[str, str] = {}
    for name, recs in by_name.items():
        if len(recs) == 1:
            out[name] = recs[0]["sha256"]
            continue
        stem, dot, suffix = name.rpartition(".")
        if not stem:
            stem, dot, suffix = name, "", ""
        for r in recs:
            out[f"{stem}.{r['origin']}-{r['sha256'][:8]}{dot}{suffix}"] = r["sha256"]
    return out


def listing(records) -> list[dict]:
    """`ccrp knowledge list`: the live items, by name then origin."""
    return sorted(({"name": r["name"], "sha256": r["sha256"], "size": r["size"], "origin": r["origin"],
                    "added": r["added"]} for r in records if live(r)),
                  key=lambda r: (r["name"], r["origin"], r["sha256"]))


# -- a dataset on disk ---------------------------------------------------------------------------

def write_atomic(path: str, data: bytes) -> None:
    """`data` as the file at `path`, whole or not at all; a write that fails (a full disk) leaves
    the old file and no temporary one, and raises."""
    tmp = f"{path}.tmp"
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


class Dataset:
    def __init__(self, root: str, name: str, report=log) -> None:
        self.name, self.dir, self.report = name, os.path.join(root, name), report
        for sub in ("objects", "files", "tmp"):
            os.makedirs(os.path.join(self.dir, sub), exist_ok=True)
        # A transfer cut by a crash left its temporary file only: nothing of it was ever an item.
        for left in os.listdir(os.path.join(self.dir, "tmp")):
            os.unlink(os.path.join(self.dir, "tmp", left))
        self.index: dict[tuple[str, str], dict] = {}
        try:
            with open(os.path.join(self.dir, "index.json")) as fh:
                for rec in json.load(fh):
                    if valid(rec):
                        self.index[key(rec)] = rec
        except FileNotFoundError:
            pass
        # An index that names a live item whose object is gone (removed by hand) forgets the add,
        # so the next reconciliation fetches it again.
        for k, rec in list(self.index.items()):
            if live(rec) and not self.has(rec["sha256"]):
                del self.index[k]
        self.refresh()

    def object(self, sha: str) -> str:
        return os.path.join(self.dir, "objects", sha)

    def has(self, sha: str) -> bool:
        return os.path.exists(self.object(sha))

    def store(self, data: bytes, expect: str | None = None) -> str:
        """Write `data` as an object: temp file, fsync, hash checked, renamed into place."""
        sha = hashlib.sha256(data).hexdigest()
        if expect is not None and sha != expect:
            raise ValueError(f"content hashes to {sha[:12]}, not {expect[:12]}")
        if not self.has(sha):
            tmp = os.path.join(self.dir, "tmp", f"{sha}.{os.getpid()}.{threading.get_ident()}")
            try:
                with open(tmp, "wb") as fh:
                    fh.write(data)
                    fh.flush()
                    os.fsync(fh.fileno())
                os.replace(tmp, self.object(sha))
            except BaseException:  # a full disk: what was written of it goes, the caller reports
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
                raise
        return sha

    def save(self) -> None:
        records = sorted(self.index.values(), key=key)
        write_atomic(os.path.join(self.dir, "index.json"), json.dumps(records, sort_keys=True).encode())
        self.refresh()

    def refresh(self) -> None:
        """files/ as the live items, and objects no live item needs removed. An entry the file
        system refuses (an OSError: a name too long for it, a full disk, a directory put in the
        way) is reported and skipped: the rest is done, and the agent, which refreshes at every
        start, keeps running instead of failing on the same record again and again."""
        want = view_names(self.index.values())
        files = os.path.join(self.dir, "files")
        for name in os.listdir(files):
            path = os.path.join(files, name)
            sha = want.get(name)
            try:
                if sha is None or os.stat(path).st_ino != os.stat(self.object(sha)).st_ino:
                    os.unlink(path)
            except OSError as exc:
                self.skipped(f"files/{name}", exc)
        for name, sha in want.items():
            path = os.path.join(files, name)
            if not os.path.exists(path):
                tmp = os.path.join(self.dir, "tmp", f"link.{os.getpid()}")
                try:
                    os.link(self.object(sha), tmp)
                    os.replace(tmp, path)
                except OSError as exc:
                    self.skipped(f"files/{name}", exc)
                    with contextlib.suppress(OSError):
                        os.unlink(tmp)  # else the next item's link would find it there (EEXIST)
        needed = {r["sha256"] for r in self.index.values() if live(r)}
        for sha in os.listdir(os.path.join(self.dir, "objects")):
            if sha not in needed:
                try:
                    os.unlink(self.object(sha))
                except OSError as exc:
                    self.skipped(f"objects/{sha}", exc)

    def skipped(self, what: str, exc: OSError) -> None:
        self.report(f"{self.name}: skipped {what!r:.120}: {exc.strerror or exc}")

    def absorb(self, rec: dict) -> bool:
        """Merge a record whose object (if it makes the item live) is here. True when it changed."""
        k = key(rec)
        new = merge(self.index.get(k), rec)
        if new == self.index.get(k):
            return False
        self.index[k] = new
        return True

    def missing(self, rec: dict) -> bool:
        """Whether merging `rec` would make an item live whose object this clone lacks."""
        return live(merge(self.index.get(key(rec)), rec)) and not self.has(rec["sha256"])

    def stats(self) -> dict:
        recs = list(self.index.values())
        return {"items": sum(1 for r in recs if live(r)), "tombstones": sum(1 for r in recs if not live(r)),
                "bytes": sum(r["size"] for r in recs if live(r))}

    def used(self) -> dict:
        """What counts against the quota: live items, their bytes, and records (tombstones too)."""
        s = self.stats()
        return {"items": s["items"], "bytes": s["bytes"], "records": len(self.index)}


# -- between clones ------------------------------------------------------------------------------

def zenoh_config(cfg: dict):
    import zenoh

    c = zenoh.Config()
    # A new id for each session (as relay.py's session_id): the stable part and 8 random hex digits.
    c.insert_json5("id", json.dumps(cfg["id"] + secrets.token_hex(4)))
    c.insert_json5("mode", '"peer"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps([cfg["listen"]]))
    c.insert_json5("connect/endpoints", json.dumps(sorted(p["endpoint"] for p in cfg["peers"].values())))
    tls = cfg["tls"]
    c.insert_json5("transport/link/tls", json.dumps({
        "root_ca_certificate": tls["ca"], "enable_mtls": True,
        "listen_private_key": tls["key"], "listen_certificate": tls["cert"],
        "connect_private_key": tls["key"], "connect_certificate": tls["cert"],
    }))
    c.insert_json5("access_control", json.dumps(acl(cfg)))
    # Zenoh drops a message larger than this rather than gather it in memory (its default is 1 GiB):
    # an object is at most its dataset's quota, an index at most its records (under 1 KiB each).
    c.insert_json5("transport/link/rx/max_message_size", json.dumps(max_message(cfg)))
    return c


def quota_of(cfg: dict, ds: str) -> dict:
    return {**DEFAULT_QUOTA, **cfg.get("quotas", {}).get(ds, {})}


def item_cap(cfg: dict, ds: str) -> int:
    """The most bytes one item of `ds` may have: its quota's, and never over MAX_ITEM."""
    return min(MAX_ITEM, quota_of(cfg, ds)["bytes"])


def max_message(cfg: dict) -> int:
    biggest = max((max(item_cap(cfg, ds), quota_of(cfg, ds)["items"] * RECORDS_PER_ITEM * 1024)
                   for ds in cfg["datasets"]), default=0)
    return min(MAX_ITEM, biggest) + (1 << 20)


def acl(cfg: dict) -> dict:
    """Zenoh access control, which this clone's session enforces on what each partner sends it and
    on what it sends each partner. A partner is known by the CN of its current relay certificate
    (mutual TLS) and sees only the datasets it shares: it may subscribe to and query every key of
    such a dataset, but put, reply and declare a queryable only under its own
    `<dataset>/<robot>/`, and this clone sends under its own only. So the robot a key names is the
    clone that wrote it: a partner can neither publish nor answer a query as another. (Zenoh wants
    every list non-empty.)"""
    me, peers = cfg["robot"], sorted(cfg["peers"])
    read = ["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"]
    write = ["put", "delete", "reply", "declare_queryable", "liveliness_token"]
    rules, policies, used = [], [], set()
    for i, (ds, members) in enumerate(sorted(cfg["datasets"].items())):
        space = f"ccrp/{cfg['fleet']}/knowledge/{ds}"
        partners = [j for j, p in enumerate(peers) if p in members]
        if not partners:
            continue
        rules += [{"id": f"d{i}-read", "permission": "allow", "flows": ["ingress", "egress"], "messages": read,
                   "key_exprs": [f"{space}/**"]},
                  {"id": f"d{i}-mine", "permission": "allow", "flows": ["egress"], "messages": write,
                   "key_exprs": [f"{space}/{me}/**"]}]
        for j in partners:
            rules.append({"id": f"d{i}-p{j}", "permission": "allow", "flows": ["ingress"], "messages": write,
                          "key_exprs": [f"{space}/{peers[j]}/**"]})
            policies.append({"rules": [f"d{i}-read", f"d{i}-mine", f"d{i}-p{j}"], "subjects": [f"p{j}"]})
            used.add(j)
    subjects = [{"id": f"p{j}", "cert_common_names": [cfg["peers"][peers[j]]["cn"]]} for j in sorted(used)]
    if not rules:
        rules = [{"id": "none", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
                  "key_exprs": [f"ccrp/{cfg['fleet']}/knowledge/none"]}]
        subjects, policies = [{"id": "none", "cert_common_names": [NOBODY]}], [{"rules": ["none"], "subjects": ["none"]}]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


class Agent:
    def __init__(self, cfg: dict) -> None:
        self.cfg, self.session, self.linked = cfg, None, None
        self.lock = threading.RLock()
        self.jobs: queue.Queue = queue.Queue()
        self.datasets: dict[str, Dataset] = {}
        self.decls: list = []
        self.counts = {"received": 0, "fetched": 0, "published": 0, "errors": 0, "refused": 0}
        self.last_error: str | None = None
        self.reported: set[tuple] = set()
        self.last_reconcile: float | None = None
        self.seen_peers: set[str] = set()
        self.apply(cfg)
        threading.Thread(target=self.work, name="worker", daemon=True).start()

    def k(self, ds: str, robot: str, *rest: str) -> str:
        """A key of `robot`'s under dataset `ds` (`*` for every robot's): ccrp/<fleet>/knowledge/<ds>/<robot>/..."""
        return "/".join((f"ccrp/{self.cfg['fleet']}/knowledge/{ds}", robot, *rest))

    @staticmethod
    def writer(key: str) -> str:
        """The robot a key of ours names, <ds>/<robot>/event|index: the clone that wrote it (acl)."""
        return str(key).split("/")[4]

    # -- configuration
    def apply(self, cfg: dict) -> None:
        with self.lock:
            link = (cfg["listen"], json.dumps(cfg["peers"], sort_keys=True), json.dumps(cfg["datasets"], sort_keys=True))
            self.cfg = cfg
            for ds in cfg["datasets"]:
                if ds not in self.datasets:
                    self.datasets[ds] = Dataset(cfg["root"], ds, self.error)
            for ds in set(self.datasets) - set(cfg["datasets"]):
                del self.datasets[ds]  # its files stay on disk; it is no longer shared
            if link != self.linked:
                self._open()
                self.linked = link
        log(f"datasets {sorted(self.datasets)}; peers {sorted(cfg['peers'])}")

    def _open(self) -> None:
        import zenoh

        for d in self.decls:
            d.undeclare()
        self.decls = []
        if self.session is not None:
            old, self.session = self.session, None
            try:
                old.close()
            except Exception as exc:  # noqa: BLE001 - as in relay.py: a close that times out on a gone peer
                log(f"closing the previous session: {type(exc).__name__}: {exc}")
        self.session = zenoh.open(zenoh_config(self.cfg))
        me = self.cfg["robot"]
        for ds in self.datasets:
            self.decls.append(self.session.declare_subscriber(self.k(ds, "*", "event"),
                                                              lambda s, ds=ds: self.jobs.put(("event", ds, s))))
            self.decls.append(self.session.declare_queryable(self.k(ds, me, "index"), lambda q, ds=ds: self.on_index(ds, q)))
            self.decls.append(self.session.declare_queryable(self.k(ds, me, "blob", "*"), lambda q, ds=ds: self.on_blob(ds, q)))
        self.seen_peers = set()

    # -- answering peers (Zenoh's threads)
    def on_index(self, ds: str, query) -> None:
        try:
            with self.lock:
                d = self.datasets.get(ds)
                records = list(d.index.values()) if d else []
            query.reply(self.k(ds, self.cfg["robot"], "index"), json.dumps(records).encode())
        except Exception as exc:  # noqa: BLE001 - a peer's query must not stop the agent
            self.error(f"index query: {exc}")
        finally:
            query.drop()

    def on_blob(self, ds: str, query) -> None:
        try:
            sha = str(query.key_expr).rsplit("/", 1)[-1]
            with self.lock:
                d = self.datasets.get(ds)
                path = d.object(sha) if d and SHA_RE.match(sha) and d.has(sha) else None
            if path is not None:
                with open(path, "rb") as fh:
                    data = fh.read()
                query.reply(self.k(ds, self.cfg["robot"], "blob", sha), data)
        except Exception as exc:  # noqa: BLE001
            self.error(f"blob query: {exc}")
        finally:
            query.drop()

    # -- the worker: every change to the datasets happens here, one at a time
    def work(self) -> None:
        while True:
            job = self.jobs.get()
            try:
                if job[0] == "event":
                    _, ds, sample = job
                    self.counts["received"] += 1
                    self.take(ds, json.loads(sample.payload.to_bytes()), self.writer(sample.key_expr))
                elif job[0] == "reconcile":
                    self.reconcile(job[1] if len(job) > 1 else None)
                elif job[0] == "call":
                    _, fn, box = job
                    try:
                        box["result"] = fn()
                    except Exception as exc:  # noqa: BLE001 - handed back to the caller
                        box["error"] = exc
                    box["done"].set()
            except Exception as exc:  # noqa: BLE001 - one bad job must not stop the agent
                self.error(f"{job[0]}: {type(exc).__name__}: {exc}")

    def call(self, fn, timeout: float = 120.0):
        box = {"done": threading.Event()}
        self.jobs.put(("call", fn, box))
        if not box["done"].wait(timeout):
            raise TimeoutError("the agent is busy")
        if "error" in box:
            raise box["error"]
        return box.get("result")

    def error(self, msg: str) -> None:
        self.counts["errors"] += 1
        self.last_error = msg[:300]
        log(msg)

    def refuse(self, what: tuple, msg: str) -> None:
        """Count a peer's record refused, and report it the first time: the same record comes
        again at every reconciliation, and the log must not fill with it."""
        self.counts["refused"] += 1
        if what in self.reported:
            return
        if len(self.reported) >= REPORTED:
            self.reported.clear()
        self.reported.add(what)
        self.error(msg)

    def fetch(self, ds: str, rec: dict, holder: str) -> bytes | None:
        """The object of `rec`, asked of `holder` (who sent the record), then of any partner that
        holds it: objects are named by their hash, so any copy that hashes right is the one the
        record names, and the record itself still came from who may vouch for it. Zenoh's peer
        routing can lose a partner's queryable for seconds after another peer leaves or a session
        reopens, while its events still arrive (eclipse-zenoh/zenoh#2517, #2767): seen here as a
        fetch from the record's sender with no reply within 30 s after `fleet scale` removed a
        robot. Each try is bounded by the item's size (5 s plus 1 s a MB, at most FETCH_TIMEOUT)."""
        if holder == self.cfg["robot"]:
            return None
        timeout = min(FETCH_TIMEOUT, 5.0 + rec["size"] / 1e6)
        for attempt, who in enumerate((holder, "*", "*")):
            if attempt:
                time.sleep(1.0)
            data = self._ask(ds, rec, who, timeout)
            if data is not None:
                return data
        return None

    def _ask(self, ds: str, rec: dict, who: str, timeout: float) -> bytes | None:
        """The object of `rec` from `who` (a partner, or `*`: every partner, the first good copy),
        if one answers with the content the record names: its size (checked before the bytes are
        copied out of Zenoh's buffer) and its hash."""
        import zenoh

        sha, size = rec["sha256"], rec["size"]
        target = zenoh.QueryTarget.ALL if who == "*" else zenoh.QueryTarget.BEST_MATCHING
        for reply in self.session.get(self.k(ds, who, "blob", sha), target=target, timeout=timeout):
            if reply.ok is None:
                continue
            sender = self.writer(reply.ok.key_expr)
            if len(reply.ok.payload) != size:
                self.refuse((ds, sender, "size", sha), f"{ds}: {sender} sent {len(reply.ok.payload)} bytes for "
                            f"{rec['name']!r:.120} ({sha[:12]}), whose record says {size}: dropped")
                continue
            data = reply.ok.payload.to_bytes()
            if hashlib.sha256(data).hexdigest() == sha:
                return data
            self.error(f"{ds}: {sender} sent content that does not hash to {sha[:12]}")
        return None

    def take(self, ds: str, records: list, sender: str) -> int:
        """Merge the records `sender` sent (its event, or its index): tombstones at once, a live
        item once its object is here. A record is refused (and reported once) when it is not
        well-formed, when `sender` may not vouch for it (`vouched`), when it would take the
        dataset past its quota, or when its content is not what it says; one that the disk
        refuses (ENOSPC) is skipped and reported. The others are taken either way."""
        d = self.datasets.get(ds)
        if d is None or not isinstance(records, list):
            return 0
        changed = 0
        latest = time.time() + FUTURE_S
        quota = quota_of(self.cfg, ds)
        with self.lock:
            used = d.used()
        for rec in records:
            if not valid(rec, latest):
                self.error(f"{ds}: refused a record from {sender}: {json.dumps(rec)[:120]}")
                continue
            old = d.index.get(key(rec))
            if not vouched(old, rec, sender):
                self.refuse((ds, sender, "origin", rec["origin"], key(rec)),
                            f"{ds}: {sender} sent {rec['name']!r:.120} ({rec['sha256'][:12]}) as added by "
                            f"{rec['origin']}: a clone vouches only for its own adds; dropped")
                continue
            problem = quota_problem(old, rec, used, quota)
            if problem:
                self.refuse((ds, "quota", key(rec)), f"{ds}: {rec['name']!r:.120} from {sender} not taken: {problem}")
                continue
            if d.missing(rec):
                data = self.fetch(ds, rec, sender)
                if data is None:
                    self.error(f"{ds}: {rec['name']} ({rec['sha256'][:12]}) not fetched from {sender} or another "
                               "partner; the next reconciliation tries again")
                    continue
                try:
                    with self.lock:
                        d.store(data, rec["sha256"])
                except OSError as exc:  # a full disk: this item waits for the next reconciliation
                    d.skipped(f"objects/{rec['sha256']}", exc)
                    continue
                self.counts["fetched"] += 1
            with self.lock:
                changed += d.absorb(rec)
                account(used, old, d.index[key(rec)])
        if changed:
            self.save(d)
        return changed

    def save(self, d: Dataset) -> bool:
        """index.json and files/ written; a disk that refuses is reported, and the index kept in
        memory is written at the next change."""
        try:
            with self.lock:
                d.save()
            return True
        except OSError as exc:
            d.skipped("index.json", exc)
            return False

    def reconcile(self, only: str | None = None) -> int:
        import zenoh

        changed = 0
        for ds in sorted(self.datasets):
            if only and ds != only:
                continue
            for reply in self.session.get(self.k(ds, "*", "index"), target=zenoh.QueryTarget.ALL, timeout=10.0):
                if reply.ok is None:
                    continue
                peer = self.writer(reply.ok.key_expr)
                if peer == self.cfg["robot"]:
                    continue
                changed += self.take(ds, json.loads(reply.ok.payload.to_bytes()), peer)
        self.last_reconcile = time.time()
        return changed

    def publish(self, ds: str, records: list[dict]) -> None:
        self.session.put(self.k(ds, self.cfg["robot"], "event"), json.dumps(records).encode())
        self.counts["published"] += 1

    # -- local requests (the control socket's thread, run by the worker)
    def request(self, req: dict, data: bytes | None) -> dict:
        op, ds = req.get("op"), req.get("dataset")
        if op == "ping":
            return {"ok": True}
        if ds not in self.datasets:
            return {"ok": False, "error": f"dataset {ds!r} is not shared with this clone"}
        d = self.datasets[ds]
        if op == "list":
            with self.lock:
                return {"ok": True, **d.stats(), "items": listing(d.index.values())}
        if op == "add":
            name = req.get("name")
            problem = name_problem(name)
            if problem:
                return {"ok": False, "error": f"bad item name {str(name)[:80]!r}: {problem}"}
            data = data or b""
            with self.lock:
                sha = hashlib.sha256(data).hexdigest()
                rec = added(d.index, name, sha, len(data), self.cfg["robot"], time.time())
                problem = quota_problem(d.index.get(key(rec)), rec, d.used(), quota_of(self.cfg, ds))
                if problem:
                    return {"ok": False, "error": f"dataset {ds!r} is full: {problem}"}
                try:
                    d.store(data, sha)
                except OSError as exc:
                    return {"ok": False, "error": f"cannot store {name!r:.120} on this clone: {exc.strerror or exc}"}
                fresh = d.absorb(rec)
            if not self.save(d):
                return {"ok": False, "error": f"cannot write dataset {ds!r}'s index on this clone: {self.last_error}"}
            self.publish(ds, [rec])
            return {"ok": True, "item": {"name": name, "sha256": sha, "size": rec["size"], "origin": rec["origin"]},
                    "new": bool(fresh)}
        if op == "remove":
            target = req.get("item")
            with self.lock:
                hit = [r for r in d.index.values() if live(r) and (r["name"] == target or r["sha256"] == target)]
                recs = [removed(r, time.time()) for r in hit]
                for r in recs:
                    d.absorb(r)
            if recs:
                self.save(d)
                self.publish(ds, recs)
            return {"ok": True, "removed": [{"name": r["name"], "sha256": r["sha256"], "origin": r["origin"]} for r in recs]}
        if op == "sync":
            changed = self.reconcile(ds)
            with self.lock:
                return {"ok": True, "changed": changed, **d.stats()}
        return {"ok": False, "error": f"unknown request {str(op)[:40]!r}"}

    def status(self) -> dict:
        ids = [str(z) for z in self.session.info.peers_zid()] if self.session else []
        with self.lock:
            datasets = {ds: d.stats() for ds, d in self.datasets.items()}
        return {"time": time.time(),
                "peers": {n: any(z.startswith(p["id"]) for z in ids) for n, p in self.cfg["peers"].items()},
                "datasets": datasets, **self.counts, "last_error": self.last_error,
                "last_reconcile": self.last_reconcile}

    def watch_peers(self) -> None:
        """A peer that (re)connected may have missed events: pull its index now, not in 5 minutes."""
        connected = {str(z) for z in self.session.info.peers_zid()} if self.session else set()
        if connected - self.seen_peers:
            self.jobs.put(("reconcile",))
        self.seen_peers = connected


def read_exactly(conn: socket.socket, n: int) -> bytes:
    chunks, left = [], n
    while left:
        chunk = conn.recv(min(left, 1 << 20))
        if not chunk:
            raise ConnectionError("the client went away mid-item")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def serve(agent: Agent, path: str) -> None:
    """The control socket: one JSON line in (then `size` bytes for an add), one JSON line out."""
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o177)
    srv.bind(path)
    os.umask(old)
    srv.listen(8)
    while True:
        conn, _ = srv.accept()
        with conn:
            try:
                f = conn.makefile("rb")
                req = json.loads(f.readline(65536))
                data = None
                if req.get("op") == "add":
                    size = int(req.get("size", -1))
                    # Never more in memory than the dataset's quota lets one item have.
                    cap = item_cap(agent.cfg, req.get("dataset")) if req.get("dataset") in agent.datasets else 0
                    if not 0 <= size <= cap:
                        raise ValueError(f"an item of {size} bytes: dataset {str(req.get('dataset'))[:40]!r} here "
                                         f"takes up to {cap}")
                    data = f.read(size)
                    if len(data) != size:
                        raise ConnectionError("the client went away mid-item")
                reply = agent.call(lambda: agent.request(req, data))
            except Exception as exc:  # noqa: BLE001 - answered, not fatal
                reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            try:
                conn.sendall(json.dumps(reply).encode() + b"\n")
            except OSError:
                pass


def ctl(argv: list[str]) -> int:
    """`knowledge.py ctl REQUEST [FILE]`: one request to the running agent; FILE (base64, removed
    afterwards) is the item's content for an add. Prints the agent's JSON answer."""
    req = json.loads(argv[0])
    data = b""
    if len(argv) > 1:
        # The spool file lies in the agent user's directory: take it only if it is a regular file of
        # ours (root's, as ccrp pushed it), not a link the agent's user put in its place.
        fd = os.open(argv[1], os.O_RDONLY | os.O_NOFOLLOW)
        with os.fdopen(fd, "rb") as fh:
            st = os.fstat(fh.fileno())
            if not stat.S_ISREG(st.st_mode) or st.st_uid != os.geteuid():
                print(json.dumps({"ok": False, "error": "the spooled item is not the file ccrp pushed"}))
                return 1
            data = base64.b64decode(fh.read(), validate=True)
        os.unlink(argv[1])
        req["size"] = len(data)
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        s.connect(req.pop("socket", SOCKET))
    except OSError as exc:
        print(json.dumps({"ok": False, "error": f"the knowledge agent is not running ({exc.strerror})"}))
        return 3
    with s:
        s.sendall(json.dumps(req).encode() + b"\n" + data)
        reply = s.makefile("rb").readline()
    print(reply.decode().strip() or json.dumps({"ok": False, "error": "no answer from the agent"}))
    return 0 if json.loads(reply or b"{}").get("ok") else 1


def wait_for_files(cfg: dict) -> None:
    while not all(os.access(cfg["tls"][k], os.R_OK) for k in ("ca", "cert", "key")):
        time.sleep(1)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "ctl":
        sys.exit(ctl(sys.argv[2:]))
    path = sys.argv[1] if len(sys.argv) > 1 else DEFAULT_CONFIG
    while not os.path.exists(path):
        time.sleep(1)
    mtime = os.stat(path).st_mtime
    with open(path) as fh:
        cfg = json.load(fh)
    wait_for_files(cfg)
    agent = Agent(cfg)
    threading.Thread(target=serve, args=(agent, cfg.get("socket", SOCKET)), name="ctl", daemon=True).start()
    log(f"{cfg['robot']}: listening on {cfg['listen']}")
    agent.jobs.put(("reconcile",))
    next_reconcile = time.monotonic() + cfg["reconcile"]
    while True:
        try:
            changed = os.stat(path).st_mtime
            if changed != mtime:
                with open(path) as fh:
                    agent.apply(json.load(fh))
                mtime = changed  # only once applied: a config that failed is applied again next second
            agent.watch_peers()
            if time.monotonic() >= next_reconcile:
                agent.jobs.put(("reconcile",))
                next_reconcile = time.monotonic() + agent.cfg["reconcile"]
            write_atomic(cfg["status"], json.dumps(agent.status()).encode())
        except Exception as exc:  # noqa: BLE001 - keep going; report and retry next second
            agent.error(f"{type(exc).__name__}: {exc}")
        time.sleep(1)


if __name__ == "__main__":
    main()
