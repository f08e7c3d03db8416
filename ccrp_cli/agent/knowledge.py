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
  ccrp/<fleet>/knowledge/<ds>/event/<robot>      records a clone just changed (put)
  ccrp/<fleet>/knowledge/<ds>/index/<robot>      queryable: that clone's whole index
  ccrp/<fleet>/knowledge/<ds>/blob/<robot>/<sha> queryable: one object's bytes
A record that makes an item live is merged only once its object is here: fetched to tmp/, its
hash checked, then renamed into objects/ (a transfer cut anywhere leaves no item). Every
`reconcile` seconds, when a peer (re)connects and on `sync`, the agent pulls every peer's index.

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
    tmp = f"{path}.tmp"
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


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
            with open(tmp, "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.object(sha))
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


# -- between clones ------------------------------------------------------------------------------

def zenoh_config(cfg: dict):
    import zenoh

    c = zenoh.Config()
    c.insert_json5("id", json.dumps(cfg["id"]))
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
    return c


def acl(cfg: dict) -> dict:
    """Zenoh access control: a dataset's keys are open only to the clones sharing it, each admitted
    by the CN of its current relay certificate (Zenoh wants every list non-empty)."""
    rules, subjects, policies = [], [], []
    for i, (ds, members) in enumerate(sorted(cfg["datasets"].items())):
        cns = sorted(cfg["peers"][m]["cn"] for m in members if m in cfg["peers"]) or [NOBODY]
        rules.append({"id": f"r{i}", "permission": "allow", "flows": ["ingress", "egress"],
                      "messages": ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                                   "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"],
                      "key_exprs": [f"ccrp/{cfg['fleet']}/knowledge/{ds}/**"]})
        subjects.append({"id": f"s{i}", "cert_common_names": cns})
        policies.append({"rules": [f"r{i}"], "subjects": [f"s{i}"]})
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
        self.counts = {"received": 0, "fetched": 0, "published": 0, "errors": 0}
        self.last_error: str | None = None
        self.last_reconcile: float | None = None
        self.seen_peers: set[str] = set()
        self.apply(cfg)
        threading.Thread(target=self.work, name="worker", daemon=True).start()

    def k(self, ds: str, *rest: str) -> str:
        return "/".join((f"ccrp/{self.cfg['fleet']}/knowledge/{ds}", *rest))

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
            self.session.close()
            self.session = None
        self.session = zenoh.open(zenoh_config(self.cfg))
        me = self.cfg["robot"]
        for ds in self.datasets:
            self.decls.append(self.session.declare_subscriber(self.k(ds, "event", "*"),
                                                              lambda s, ds=ds: self.jobs.put(("event", ds, s))))
            self.decls.append(self.session.declare_queryable(self.k(ds, "index", me), lambda q, ds=ds: self.on_index(ds, q)))
            self.decls.append(self.session.declare_queryable(self.k(ds, "blob", me, "*"), lambda q, ds=ds: self.on_blob(ds, q)))
        self.seen_peers = set()

    # -- answering peers (Zenoh's threads)
    def on_index(self, ds: str, query) -> None:
        try:
            with self.lock:
                d = self.datasets.get(ds)
                records = list(d.index.values()) if d else []
            query.reply(self.k(ds, "index", self.cfg["robot"]), json.dumps(records).encode())
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
                query.reply(self.k(ds, "blob", self.cfg["robot"], sha), data)
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
                    sender = str(sample.key_expr).rsplit("/", 1)[-1]
                    self.take(ds, json.loads(sample.payload.to_bytes()), [sender])
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

    def fetch(self, ds: str, sha: str, holders: list[str]) -> bytes | None:
        """An object's bytes from the first holder that answers with the right content."""
        for holder in holders:
            if holder == self.cfg["robot"]:
                continue
            for reply in self.session.get(self.k(ds, "blob", holder, sha), timeout=FETCH_TIMEOUT):
                if reply.ok is not None:
                    data = reply.ok.payload.to_bytes()
                    if hashlib.sha256(data).hexdigest() == sha:
                        return data
                    self.error(f"{ds}: {holder} sent content that does not hash to {sha[:12]}")
        return None

    def take(self, ds: str, records: list, holders: list[str]) -> int:
        """Merge peers' records: tombstones at once, a live item once its object is here."""
        d = self.datasets.get(ds)
        if d is None or not isinstance(records, list):
            return 0
        changed = 0
        latest = time.time() + FUTURE_S
        for rec in records:
            if not valid(rec, latest):
                self.error(f"{ds}: refused a record from {holders}: {json.dumps(rec)[:120]}")
                continue
            if d.missing(rec):
                data = self.fetch(ds, rec["sha256"], holders)
                if data is None:
                    self.error(f"{ds}: {rec['name']} ({rec['sha256'][:12]}) not fetched from {holders}; "
                               "the next reconciliation tries again")
                    continue
                with self.lock:
                    d.store(data, rec["sha256"])
                self.counts["fetched"] += 1
            with self.lock:
                changed += d.absorb(rec)
        if changed:
            with self.lock:
                d.save()
        return changed

    def reconcile(self, only: str | None = None) -> int:
        import zenoh

        changed = 0
        for ds in sorted(self.datasets):
            if only and ds != only:
                continue
            for reply in self.session.get(self.k(ds, "index", "*"), target=zenoh.QueryTarget.ALL, timeout=10.0):
                if reply.ok is None:
                    continue
                peer = str(reply.ok.key_expr).rsplit("/", 1)[-1]
                if peer == self.cfg["robot"]:
                    continue
                changed += self.take(ds, json.loads(reply.ok.payload.to_bytes()), [peer])
        self.last_reconcile = time.time()
        return changed

    def publish(self, ds: str, records: list[dict]) -> None:
        self.session.put(self.k(ds, "event", self.cfg["robot"]), json.dumps(records).encode())
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
            with self.lock:
                sha = d.store(data or b"")
                rec = added(d.index, name, sha, len(data or b""), self.cfg["robot"], time.time())
                fresh = d.absorb(rec)
                d.save()
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
                    d.save()
            if recs:
                self.publish(ds, recs)
            return {"ok": True, "removed": [{"name": r["name"], "sha256": r["sha256"], "origin": r["origin"]} for r in recs]}
        if op == "sync":
            changed = self.reconcile(ds)
            with self.lock:
                return {"ok": True, "changed": changed, **d.stats()}
        return {"ok": False, "error": f"unknown request {str(op)[:40]!r}"}

    def status(self) -> dict:
        connected = {str(z) for z in self.session.info.peers_zid()} if self.session else set()
        with self.lock:
            datasets = {ds: d.stats() for ds, d in self.datasets.items()}
        return {"time": time.time(), "peers": {n: p["id"] in connected for n, p in self.cfg["peers"].items()},
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
                    if not 0 <= size <= MAX_ITEM:
                        raise ValueError(f"bad size {size}")
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
            if os.stat(path).st_mtime != mtime:
                mtime = os.stat(path).st_mtime
                with open(path) as fh:
                    agent.apply(json.load(fh))
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
