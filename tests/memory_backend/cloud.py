"""The memory backend's cloud: every resource in one dict, behind API calls that count
themselves and can be slowed down or throttled before they reach the state, as the harnesses of
the real backends do to their SDKs' fakes. One cloud per process (CLOUD), as a real one outlives
each provider a command makes; `fresh()` starts an empty one (each contract test does)."""

from __future__ import annotations

import functools
import hashlib
import itertools
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

from ccrp_cli.models.layout import AUTOSTOP_MARK


class Throttled(Exception):
    """The cloud shed load (an HTTP 429): the provider retries."""


class Refused(Exception):
    """A real answer of the cloud (not found, not allowed): retrying cannot help."""


@dataclass
class Resource:
    kind: str  # an OwnedResource.kind: instance, address, firewall, network, image
    id: str
    name: str
    labels: dict[str, str]
    # instance: state, user_data, public_ip, common_ip, fs, console, restarted;
    # address: ip, instance; firewall: rules; image: fs, created
    data: dict = field(default_factory=dict)


def _api(fn):
    """An API call: counted, delayed and maybe throttled first, then run under the cloud's lock."""

    @functools.wraps(fn)
    def call(self: MemoryCloud, *args, **kwargs):
        with self._lock:
            self.calls[fn.__name__] += 1
            self._n += 1
            throttled = int(self._n * self.fraction) > int((self._n - 1) * self.fraction)
        if self.delay:
            time.sleep(self.delay)
        if throttled:
            raise Throttled(f"{fn.__name__}: too many requests")
        with self._lock:
            return fn(self, *args, **kwargs)

    return call


class MemoryCloud:
    def __init__(self) -> None:
        self.resources: dict[str, Resource] = {}
        self.calls: Counter = Counter()
        self.fraction, self.delay, self._n = 0.0, 0.0, 0
        self.refuse_association: set[str] = set()  # robots whose next address association is refused
        self._lock = threading.RLock()
        self._ids = itertools.count(1)
        self._ips = itertools.count(10)

    def add(self, kind: str, name: str, labels: dict[str, str], **data) -> Resource:
        """A resource made around the API (a harness's foreign instance, leak or base image)."""
        with self._lock:
            res = Resource(kind, f"{kind[:3]}-{next(self._ids):06d}", name, dict(labels), data)
            self.resources[res.id] = res
            return res

    def _get(self, resource_id: str) -> Resource:
        res = self.resources.get(resource_id)
        if res is None:
            raise Refused(f"{resource_id} not found")
        return res

    # -- the API ------------------------------------------------------------------------------
    @_api
    def describe(self, kind: str | None = None, labels: dict[str, str] | None = None) -> list[Resource]:
        return [r for r in self.resources.values()
                if (kind is None or r.kind == kind) and all(r.labels.get(k) == v for k, v in (labels or {}).items())]

    @_api
    def get(self, resource_id: str) -> Resource:
        return self._get(resource_id)

    @_api
    def create(self, kind: str, name: str, labels: dict[str, str], **data) -> Resource:
        if kind == "address":
            data["ip"] = f"203.0.113.{next(self._ips)}"
        return self.add(kind, name, labels, **data)

    @_api
    def delete(self, resource_id: str) -> None:
        res = self.resources.pop(self._get(resource_id).id)
        if res.kind == "address" and res.data.get("instance") in self.resources:
            self.resources[res.data["instance"]].data["public_ip"] = None

    @_api
    def associate(self, address_id: str, instance_id: str) -> None:
        address, instance = self._get(address_id), self._get(instance_id)
        robot = instance.labels.get("ccrp-robot")
        if robot in self.refuse_association:
            self.refuse_association.discard(robot)
            raise Refused(f"address {address_id}: association with {instance_id} refused")
        address.data["instance"], instance.data["public_ip"] = instance.id, address.data["ip"]

    @_api
    def set_state(self, instance_id: str, state: str) -> None:
        """Start ("running") or stop ("stopped") an instance; a boot marks the console, as
        ccrp's autostop agent does on a cloud's."""
        instance = self._get(instance_id)
        instance.data["state"] = state
        if state == "running":
            instance.data["console"].append(f"{AUTOSTOP_MARK} boot")

    @_api
    def capture(self, instance_id: str, name: str, labels: dict[str, str]) -> Resource:
        """An image of the instance's disk (its filesystem dict)."""
        fs = dict(self._get(instance_id).data["fs"])
        return self.add("image", name, labels, fs=fs, created=time.strftime("%Y-%m-%dT%H:%M:%S"))

    @_api
    def run(self, instance_id: str, argv: list[str]) -> tuple[int, str]:
        """argv on the instance, answered from its filesystem dict: cat, sha256sum, mkdir, true.
        Any other command is not found (127), as in a shell: nothing here runs a program."""
        fs = self._get(instance_id).data["fs"]
        cmd, args = argv[0], argv[1:]
        if cmd in ("true", "mkdir"):
            return 0, ""
        if cmd in ("cat", "sha256sum"):
            out, rc = [], 0
            for path in args:
                if path not in fs:
                    out.append(f"{cmd}: {path}: No such file or directory")
                    rc = 1
                elif cmd == "cat":
                    out.append(fs[path][0])
                else:
                    out.append(f"{hashlib.sha256(fs[path][0].encode()).hexdigest()}  {path}")
            return rc, "\n".join(out) + ("\n" if out else "")
        return 127, f"{cmd}: command not found (memory backend)"

    @_api
    def write(self, instance_id: str, files: list[tuple[str, str, int, str]], restart: list[str]) -> None:
        instance = self._get(instance_id)
        for dest, content, mode, group in files:
            instance.data["fs"][dest] = (content, mode, group)
        instance.data["restarted"].extend(restart)


CLOUD = MemoryCloud()


def fresh() -> MemoryCloud:
    """An empty cloud for what follows (a test of its own)."""
    global CLOUD
    CLOUD = MemoryCloud()
    return CLOUD

