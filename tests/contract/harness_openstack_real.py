"""The contract harness on the REAL OpenStack of this machine (scripts/openstack.sh, clouds.yaml
entry `ccrp-aio`: project ccrp, user ccrp; docs/openstack.md "The provider contract on the real
cloud"). Opt-in: it skips unless CCRP_E2E_OPENSTACK_REAL=1 and the cloud answers, so the contract
suite of CI skips it. Its pytest id is `openstack_real`; its kind is `openstack` (the provider's).

Clones are real Nova servers of flavor `ccrp.small`, booted from the tiny VM of the libvirt harness
(tests/tiny_vm.py: Debian's cloud kernel and initramfs, a busybox root that powers off at the ACPI
button): uploaded to Glance once per run as aki/ari images and a root image naming them
(`kernel_id`, `ramdisk_id`, `os_command_line`), deleted at the process's end. Every fleet is
`ct<run><n>` (a run's own, one per test), so nothing collides with other fleets on the same cloud;
the harness reads and deletes only what it or its provider made.

Faults are injected on the provider's own HTTP transport (a requests adapter mounted on the
keystoneauth session of `provider.client.conn`), before a request leaves the process: throttling answers
503/429 for a fraction of the service calls, the marked robot's floating-IP POST answers Neutron's
400, and `api_calls` counts what the transport saw. The cloud is read around the provider with
connections of the harness's own (the project's, and the admin's for a server's user-data)."""

from __future__ import annotations

import atexit
import json
import os
import re
import threading
import time
import uuid
from collections import Counter
from contextlib import contextmanager
from urllib.parse import urlparse

import pytest

from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE
from ccrp_cli.retry import Backoff

from ..tiny_vm import CMDLINE, tiny_files
from .harness_openstack import public_ingress
from .specs import OPERATOR_CIDR, clone_spec, inventory

CLOUD = "ccrp-aio"
ADMIN_CLOUD = "ccrp-aio-admin"
FLAVOR = "ccrp.small"
EXTERNAL = "public"
SWITCH = "CCRP_E2E_OPENSTACK_REAL"
RUN = uuid.uuid4().hex[:5]  # this process's fleets are ct<RUN><n>; its images ccrp-ct<RUN>-tiny-*
POLL = 1.0  # s between status checks: a tiny server is ACTIVE in ~20 s under TCG
# The cloud is real but the throttling is injected: many quick attempts, as the fake's FAST, but
# with room for a real transient error.
BACKOFF = Backoff(attempts=20, base=0.01, cap=0.5)
SERVICES = {5000: "identity", 8774: "compute", 9696: "network", 9292: "image", 8778: "placement"}
_ID = re.compile(r"/[0-9a-f]{8}-?[0-9a-f]{4}-?[0-9a-f]{4}-?[0-9a-f]{4}-?[0-9a-f]{12}(?=/|$)")


def gate() -> str | None:
    """Why the real cloud cannot be used (pytest's skip reason), or None."""
    if os.environ.get(SWITCH) != "1":
        return f"the real OpenStack is opt-in: {SWITCH}=1 (make contract-openstack-real)"
    try:
        import openstack

        conn = openstack.connect(cloud=CLOUD, api_timeout=20)
        conn.authorize()
        conn.close()
    except Exception as exc:  # noqa: BLE001 - any failure: the cloud does not answer
        return f"cloud {CLOUD!r} does not answer ({type(exc).__name__}: {str(exc)[:120]}): bash scripts/openstack.sh"
    return None


def connect(cloud: str = CLOUD):
    import openstack

    return openstack.connect(cloud=cloud)


# -- the tiny image in Glance, once per process -------------------------------------------------
_IMAGES: dict[str, str] = {}
_IMAGES_LOCK = threading.Lock()


def upload_image(conn, name: str, path, disk_format: str, container_format: str, **props) -> str:
    """An image uploaded as the project's (Glance's default visibility, `shared`); its id."""
    image = conn.image.create_image(name=name, filename=str(path), disk_format=disk_format,
                                    container_format=container_format, allow_duplicates=True, wait=True,
                                    timeout=300, **props)
    return image.id


def tiny_root(conn, name: str) -> str:
    """A root image of the tiny VM, named `name`, booting the run's kernel and ramdisk (uploaded
    once per process). Returns its id."""
    from tests.e2e.fleet import ensure_base

    import docker

    with _IMAGES_LOCK:
        if not _IMAGES:
            client = docker.from_env()
            try:
                ensure_base(client)
                files = tiny_files(client)
            finally:
                client.close()
            _IMAGES["qcow2"] = str(files["qcow2"])
            atexit.register(_delete_images)
            _IMAGES["kernel"] = upload_image(conn, f"ccrp-ct{RUN}-tiny-kernel", files["kernel"], "aki", "aki")
            _IMAGES["ramdisk"] = upload_image(conn, f"ccrp-ct{RUN}-tiny-ramdisk", files["initrd"], "ari", "ari")
        if f"root:{name}" in _IMAGES:
            return _IMAGES[f"root:{name}"]
        image_id = upload_image(conn, name, _IMAGES["qcow2"], "qcow2", "bare", kernel_id=_IMAGES["kernel"],
                                ramdisk_id=_IMAGES["ramdisk"], os_command_line=CMDLINE)
        _IMAGES[f"root:{name}"] = image_id
        return image_id


def shared_ids() -> list[str]:
    """The kernel and ramdisk images (another project booting the root image needs them too)."""
    return [_IMAGES["kernel"], _IMAGES["ramdisk"]]


def _delete_images() -> None:
    """At the process's end: the root images first, then the kernel and ramdisk they name."""
    import sys

    conn = connect()
    try:
        for key, image_id in sorted(_IMAGES.items(), key=lambda kv: not kv[0].startswith("root:")):
            if key == "qcow2":
                continue
            try:
                conn.image.delete_image(image_id, ignore_missing=True)
            except Exception as exc:  # noqa: BLE001 - the others still go; this one is said
                print(f"harness_openstack_real: image {image_id} not deleted: {exc}", file=sys.stderr)
    finally:
        conn.close()


# -- faults on the provider's transport ---------------------------------------------------------
def _http_adapter(harness):
    from requests.adapters import HTTPAdapter
    from requests.models import Response

    def answer(request, status: int, body: dict) -> Response:
        r = Response()
        r.status_code, r.reason, r.url, r.request, r.encoding = status, "injected", request.url, request, "utf-8"
        r._content = json.dumps(body).encode()
        r.headers["Content-Type"] = "application/json"
        r.headers["Retry-After"] = "0"
        return r

    class Faults(HTTPAdapter):
        """Counts, delays and fails requests before they leave the process."""

        def send(self, request, **kwargs):
            url = urlparse(request.url)
            service = SERVICES.get(url.port, url.netloc)
            op = f"{request.method} {service}:{_ID.sub('/{id}', url.path.rstrip('/'))}"
            with harness._lock:
                harness.calls[op] += 1
                throttled = service != "identity" and harness._throttled()
                fail = (request.method == "POST" and service == "network" and url.path.endswith("/floatingips")
                        and harness._take_fip_failure(request.body))
            if harness._delay:
                time.sleep(harness._delay)
            if throttled:
                status = 429 if harness._n % 2 else 503
                return answer(request, status, {"message": "Rate limit exceeded" if status == 429 else "Service Unavailable"})
            if fail:
                return answer(request, 400, {"NeutronError": {"type": "BadRequest", "detail": "", "message":
                              "injected: External network is not reachable from subnet of port"}})
            if harness.before is not None:
                harness.before(request.method, service, url.path)
            return super().send(request, **kwargs)

    return Faults()


def _owned(labels: dict | None, fleet: str, robot: str | None) -> bool:
    labels = labels or {}
    return (labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == fleet
            and (robot is None or labels.get(LABEL_ROBOT) == robot))


def tags_of(res) -> dict:
    return dict(t.split("=", 1) for t in (res.tags or []) if "=" in t)


def fleet_resources(conn, fleet: str, robot: str | None = None) -> dict[str, str]:
    """{id: kind} of everything in the cloud (as `conn` sees it) carrying fleet's labels (robot's,
    if given): servers, ports, floating IPs, routers, subnets, networks, security groups, images;
    the fleet's key pair (Nova's carry no labels: known by name) unless robot is given."""
    found = {s.id: "server" for s in conn.compute.servers(name=f"^ccrp-{fleet}-")
             if s.name.startswith(f"ccrp-{fleet}-") and _owned(s.metadata, fleet, robot)}
    want = [f"{LABEL_MANAGED}=true", f"{LABEL_FLEET}={fleet}"] + ([f"{LABEL_ROBOT}={robot}"] if robot else [])
    for kind in ("ports", "ips", "routers", "subnets", "networks", "security_groups"):
        found |= {r.id: kind for r in getattr(conn.network, kind)(tags=",".join(want))}
    found |= {i.id: "image" for i in conn.image.images(tag=f"{LABEL_FLEET}={fleet}")
              if _owned(i.properties, fleet, robot)}
    if robot is None and conn.compute.find_keypair(f"ccrp-{fleet}", ignore_missing=True) is not None:
        found[f"ccrp-{fleet}"] = "key_pair"
    return found


class RealOpenStackHarness:
    kind = "openstack"

    def __init__(self, provider, cloud, admin, image_id: str) -> None:
        self.provider, self.cloud, self.admin, self.image_id = provider, cloud, admin, image_id
        self.fleet = provider.fleet
        self.calls: Counter = Counter()
        self._lock = threading.Lock()
        self._fraction, self._delay, self._n = 0.0, 0.0, 0
        self._fail_robots: set[str] = set()
        self.before = None  # (method, service, path) -> None, called before a request leaves
        self.foreign: list[str] = []
        self.leaks: list[str] = []
        for prefix in ("http://", "https://"):
            provider.client.conn.session.session.mount(prefix, _http_adapter(self))

    def _throttled(self) -> bool:
        """Every (1/fraction)-th service call, deterministically, as the fake does."""
        self._n += 1
        f = self._fraction
        return int(self._n * f) > int((self._n - 1) * f)

    def _take_fip_failure(self, body) -> bool:
        if not self._fail_robots or not body:
            return False
        text = body.decode() if isinstance(body, bytes) else str(body)
        robot = next((r for r in self._fail_robots if f"clone of {r}\"" in text), None)
        if robot is None:
            return False
        self._fail_robots.discard(robot)
        return True

    # -- knobs ----------------------------------------------------------------------------------
    def spec(self, robot: str, index: int):
        return clone_spec(self.provider.inv, robot, index, self.image_id)

    def fail_create_after_instance(self, robot: str) -> None:
        self._fail_robots.add(robot)  # the floating-IP POST after the server is ACTIVE fails

    def throttle(self, fraction: float) -> None:
        self._fraction = fraction

    def delay(self, seconds: float) -> None:
        self._delay = seconds

    def api_calls(self) -> Counter:
        return Counter(self.calls)

    # -- the cloud, read around the provider ----------------------------------------------------
    def _servers(self, robot: str | None = None) -> list:
        prefix = f"ccrp-{self.fleet}-"
        return [s for s in self.cloud.compute.servers(name=f"^{prefix}")
                if s.name.startswith(prefix) and _owned(s.metadata, self.fleet, robot)]

    def owned_ids(self, robot: str | None = None) -> set[str]:
        return set(fleet_resources(self.cloud, self.fleet, robot))

    def add_foreign(self) -> str:
        """A server named exactly like robot1's clone, labelled for another fleet, on no network
        (a port on the fleet's network would hold its subnet at teardown)."""
        server = self.cloud.compute.create_server(
            name=f"ccrp-{self.fleet}-cri-robot1", image_id=self.image_id,
            flavor_id=self.cloud.compute.find_flavor(FLAVOR, ignore_missing=False).id, networks="none",
            metadata={LABEL_MANAGED: "true", LABEL_FLEET: "other", LABEL_ROLE: "clone", LABEL_ROBOT: "robot1"})
        self.foreign.append(server.id)
        return server.id

    def add_leak(self) -> str:
        """A floating IP of the fleet left by a crash between allocation and attachment."""
        ext = self.cloud.network.find_network(EXTERNAL, ignore_missing=False)
        fip = self.cloud.network.create_ip(floating_network_id=ext.id, description=f"ccrp contract leak {self.fleet}")
        self.leaks.append(fip.id)
        self.cloud.network.set_tags(fip, [f"{LABEL_MANAGED}=true", f"{LABEL_FLEET}={self.fleet}",
                                          f"{LABEL_ROLE}=clone", f"{LABEL_ROBOT}=ghost"])
        return fip.id

    def exists(self, resource_id: str) -> bool:
        c = self.cloud
        lookups = (c.compute.find_server, c.network.find_network, c.network.find_subnet, c.network.find_router,
                   c.network.find_port, c.network.find_ip, c.network.find_security_group, c.image.find_image,
                   c.compute.find_keypair)
        for lookup in lookups:
            try:
                found = lookup(resource_id, ignore_missing=True)
            except Exception:  # noqa: BLE001 - e.g. a name that is no valid id for that service
                continue
            if found is not None and getattr(found, "status", None) != "DELETED":
                return True
        return False

    def public_ingress(self) -> set[tuple[str, int, str]]:
        want = f"{LABEL_MANAGED}=true,{LABEL_FLEET}={self.fleet}"
        groups = [{"security_group_rules": sg.security_group_rules}
                  for sg in self.cloud.network.security_groups(tags=want)]
        return public_ingress(groups, self.provider.inv.common.cidr)

    def user_data_sent(self, robot: str) -> bytes:
        """Nova's copy of the server's user-data (shown to the admin only, microversion 2.3+)."""
        import base64

        [server] = self._servers(robot)
        return base64.b64decode(self.admin.compute.get_server(server.id).user_data)

    def instance_roles(self, robot: str) -> list[str]:
        return [s.metadata.get(LABEL_ROLE, "") for s in self._servers(robot)]

    def instances_for(self, robot: str) -> int:
        return len(self._servers(robot))

    def new_provider(self, inv, workdir):
        """An OpenStackProvider of another inventory on the same cloud, its calls counted and
        faulted as the first's."""
        from ccrp_cli.providers.openstack.provider import OpenStackProvider

        provider = OpenStackProvider(inv, workdir)
        provider.client.backoff, provider.client.poll_interval = BACKOFF, POLL
        for prefix in ("http://", "https://"):
            provider.client.conn.session.session.mount(prefix, _http_adapter(self))
        return provider

    def kill(self, provider_id: str) -> None:
        """The server deleted around ccrp, as an operator does (its port and floating IP stay)."""
        server = self.cloud.compute.find_server(provider_id, ignore_missing=True)
        if server is not None:
            self.cloud.compute.delete_server(server)
            self.cloud.compute.wait_for_delete(server, interval=POLL, wait=300)

    def cleanup(self) -> None:
        """What the harness made itself (foreign servers, leaks the test left)."""
        for server_id in self.foreign:
            self.cloud.compute.delete_server(server_id, ignore_missing=True)
        for server_id in self.foreign:
            server = self.cloud.compute.find_server(server_id, ignore_missing=True)
            if server is not None:
                self.cloud.compute.wait_for_delete(server, interval=POLL, wait=300)
        for fip_id in self.leaks:
            self.cloud.network.delete_ip(fip_id, ignore_missing=True)


_FLEETS = iter(range(1, 10_000))


def new_fleet() -> str:
    return f"ct{RUN}{next(_FLEETS)}"


def make_provider(fleet: str, workdir, cloud: str = CLOUD, flavor: str = FLAVOR):
    """An OpenStackProvider of a fleet on the real cloud, polling as fits it."""
    from ccrp_cli.providers.openstack.provider import OpenStackProvider

    inv = inventory({"kind": "openstack", "cloud": cloud, "flavor": flavor, "external_network": EXTERNAL,
                     "operator_cidr": OPERATOR_CIDR}, fleet=fleet)
    provider = OpenStackProvider(inv, workdir)
    provider.client.backoff = BACKOFF
    provider.client.poll_interval = POLL
    return provider


@contextmanager
def make_harness(tmp_path):
    if reason := gate():
        pytest.skip(reason)
    cloud, admin = connect(), connect(ADMIN_CLOUD)
    image_id = tiny_root(cloud, f"ccrp-ct{RUN}-tiny")
    provider = make_provider(new_fleet(), tmp_path / "store")
    harness = RealOpenStackHarness(provider, cloud, admin, image_id)
    try:
        provider.bootstrap()
        yield harness
    finally:
        try:
            harness.throttle(0)
            harness.delay(0)
            harness._fail_robots.clear()
            harness.cleanup()
            provider.teardown()
            for snap in provider.list_snapshots():
                provider.delete_snapshot(snap.id)
            left = fleet_resources(cloud, harness.fleet)
            assert not left, f"fleet {harness.fleet} left {left} on cloud {CLOUD!r}"
        finally:
            cloud.close()
            admin.close()
