"""The contract harness on the real Docker engine. Clones run a tiny image (ccrp/base:bookworm
with `sleep` as its command: no systemd boot), so the suite tests the provider, not cloud-init.
Like a clone's systemd, its PID 1 ends on the stop signal the provider gives its containers
(SIGRTMIN+3): a bare `sleep` as PID 1 ignores it, and every stop waited out Docker's 60 s timeout.
Faults and delays are injected in the HTTP adapter under docker-py, before a request reaches the
engine (and under the provider's own retry layer, as a cloud's throttling would be)."""

from __future__ import annotations

import io
import re
import tarfile
import threading
import time
from collections import Counter
from contextlib import contextmanager

import pytest

from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE

from .harness import FLEET
from .specs import FAST, Knobs, clone_spec, inventory

BASE = "ccrp/base:bookworm"
TINY = "ccrp/contract-tiny:2"  # 2: PID 1 ends on SIGRTMIN+3
# Subnets of their own, so a fleet running on this engine is never in the way.
# Ranges of the harness's networks: a free /24 of each, picked per test (tests/scenarios/backend.py free_cidr).
PUBLIC_RANGE, COMMON_RANGE = "172.25.0.0/16", "10.197.0.0/16"
_ID = re.compile(r"/[0-9a-f]{12,64}(?=/|$)")


def _fake_response(request, status: int, message: str):
    import requests

    r = requests.Response()
    r.status_code, r.reason, r.request, r.url = status, message, request, request.url
    r.headers["Content-Type"] = "application/json"
    r._content = f'{{"message": "{message}"}}'.encode()
    return r


class DockerHarness(Knobs):
    kind = "docker"

    def __init__(self, provider) -> None:
        self.provider, self.client = provider, provider.client.engine
        self.calls: Counter = Counter()
        self._lock = threading.Lock()
        self._fraction, self._delay, self._n = 0.0, 0.0, 0
        self._fail_robots: set[str] = set()
        self._doomed: set[str] = set()
        self.foreign: list[str] = []
        adapter = provider.client.engine.api.get_adapter("http+docker://")
        self._send = adapter.send
        adapter.send = self._intercept

    def _intercept(self, request, **kwargs):
        path = request.path_url.split("?")[0]
        op = f"{request.method} {_ID.sub('/{id}', re.sub(r'^/v[0-9.]+', '', path))}"
        with self._lock:
            self.calls[op] += 1
            self._n += 1
            throttled = int(self._n * self._fraction) > int((self._n - 1) * self._fraction)
        if self._delay:
            time.sleep(self._delay)
        if throttled:
            return _fake_response(request, 429, "injected: too many requests")
        if request.method == "POST" and path.endswith("/start") and path.split("/")[-2] in self._doomed:
            return _fake_response(request, 500, "injected: cannot start container")
        response = self._send(request, **kwargs)
        robot = re.search(rf"name=ccrp-{FLEET}-cri-(\w+)", request.path_url)
        if op == "POST /containers/create" and robot and robot[1] in self._fail_robots and response.status_code == 201:
            self._fail_robots.discard(robot[1])
            self._doomed.add(response.json()["Id"])
        return response

    def spec(self, robot: str, index: int):
        return clone_spec(self.provider.inv, robot, index, TINY)

    # Read straight from the engine with its own client, around the provider.
    def _labelled(self, robot: str | None = None) -> dict:
        labels = [f"{LABEL_FLEET}={FLEET}", f"{LABEL_MANAGED}=true"] + ([f"{LABEL_ROBOT}={robot}"] if robot else [])
        return {"label": labels}

    def _clones(self, robot: str):
        f = self._labelled(robot)
        f["label"].append(f"{LABEL_ROLE}=clone")
        return self.raw.containers.list(ignore_removed=True, all=True, filters=f)

    def instance_roles(self, robot: str) -> list[str]:
        return [c.labels.get(LABEL_ROLE, "") for c in self.raw.containers.list(ignore_removed=True, all=True, filters=self._labelled(robot))]

    def instances_for(self, robot: str) -> int:
        return len(self._clones(robot))

    def owned_ids(self, robot: str | None = None) -> set[str]:
        f = self._labelled(robot)
        ids = {c.id[:12] for c in self.raw.containers.list(ignore_removed=True, all=True, filters=f)}
        ids |= {v.name for v in self.raw.volumes.list(filters=f)}
        if robot is None:
            ids |= {n.name for n in self.raw.networks.list(filters=f)}
            ids |= {i.id.removeprefix("sha256:")[:12] for i in self.raw.images.list(filters=f)}
        return ids

    def add_foreign(self) -> str:
        labels = {LABEL_MANAGED: "true", LABEL_FLEET: "other", LABEL_ROLE: "clone", LABEL_ROBOT: "robot1"}
        c = self.raw.containers.run(TINY, name=f"ccrp-{FLEET}foreign-cri-robot1", labels=labels, detach=True)
        self.foreign.append(c.id)
        return c.id[:12]

    def add_leak(self) -> str:
        # A secrets volume whose clone is gone (say, a crash between creating both).
        labels = {LABEL_MANAGED: "true", LABEL_FLEET: FLEET, LABEL_ROLE: "secrets", LABEL_ROBOT: "ghost"}
        return self.raw.volumes.create(f"ccrp-{FLEET}-cri-ghost-vpn", labels=labels).name

    def exists(self, resource_id: str) -> bool:
        from docker.errors import NotFound

        for getter in (self.raw.containers, self.raw.volumes, self.raw.images, self.raw.networks):
            try:
                getter.get(resource_id)
                return True
            except NotFound:
                continue
        return False

    def public_ingress(self) -> set[tuple[str, int, str]]:
        rules = set()
        for c in self.raw.containers.list(ignore_removed=True, all=True, filters=self._labelled()):
            for port, bindings in (c.attrs["NetworkSettings"]["Ports"] or {}).items():
                number, proto = port.split("/")
                for b in bindings or []:
                    anywhere = b["HostIp"] in ("", "0.0.0.0", "::")
                    rules.add((proto, int(number), "0.0.0.0/0" if anywhere else f"{b['HostIp']}/32"))
        return rules

    def user_data_sent(self, robot: str) -> bytes:
        stream, _ = self._clones(robot)[0].get_archive("/var/lib/cloud/seed/nocloud/user-data")
        with tarfile.open(fileobj=io.BytesIO(b"".join(stream))) as tar:
            return tar.extractfile("user-data").read()


@contextmanager
def make_harness(tmp_path):
    docker = pytest.importorskip("docker")
    try:
        raw = docker.from_env()
        raw.ping()
    except docker.errors.DockerException as exc:
        pytest.skip(f"no Docker engine ({type(exc).__name__})")
    from tests.e2e.fleet import ensure_base

    ensure_base(raw)  # a fresh machine (CI): built once, as `snapshot build` would; the e2e tests reuse it
    built = _tiny_image(raw)
    from ccrp_cli.providers.docker.provider import DockerProvider

    from tests.scenarios.backend import free_cidr

    inv = inventory({"kind": "docker", "public_cidr": free_cidr(PUBLIC_RANGE), "publish_vpn_ports": True},
                    common={"cidr": free_cidr(COMMON_RANGE)})
    provider = DockerProvider(inv, tmp_path / "store")  # its state id labels the snapshots it takes
    provider.backoff = FAST
    harness = None
    provider.teardown()  # what a killed run left of fleet "ct" on this engine (create would reuse it)
    try:
        provider.bootstrap()
        harness = DockerHarness(provider)
        harness.raw = raw
        yield harness
    finally:
        if harness:
            harness.throttle(0)
            for cid in harness.foreign:
                raw.containers.get(cid).remove(force=True)
        provider.teardown()
        for image in raw.images.list(filters={"label": [f"{LABEL_FLEET}={FLEET}"]}):
            raw.images.remove(image.id, force=True)
        if built:
            raw.images.remove(TINY)


def _tiny_image(raw) -> bool:
    """Tag the base with `sleep` as its command (no new layer), under a shell that exits on the
    stop signal as systemd would. True when this call made it."""
    try:
        raw.images.get(TINY)
        return False
    except Exception:  # noqa: BLE001 - NotFound
        pass
    data = f'FROM {BASE}\nCMD ["bash", "-c", "trap \'exit 0\' TERM RTMIN+3; sleep infinity & wait"]\n'.encode()
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        info = tarfile.TarInfo("Dockerfile")
        info.size = len(data)
        tar.addfile(info, io.BytesIO(data))
    buf.seek(0)
    raw.images.build(fileobj=buf, custom_context=True, tag=TINY, rm=True)
    return True
