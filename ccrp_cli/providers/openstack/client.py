"""The OpenStack backend's client: the connection (credentials from clouds.yaml / OS_CLOUD through
openstack.connect; ccrp never reads them), every SDK call wrapped by retry.call with errors.py's
classification, SDK failures translated into one-line CcrpErrors, the fleet's names and Neutron
tags, and the lookups the other modules of the backend share (tagged resources, the fleet's
servers, find)."""

from __future__ import annotations

import re
import threading
from pathlib import Path

from ...errors import CcrpError, translated
from ...models.inventory import Inventory
from ...retry import Backoff, call
from ..base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, owner_labels
from ..cloud import operator_public_key
from . import errors
from .settings import OpenStackSettings


def _connect(cloud: str):
    try:
        import openstack
    except ImportError:
        raise CcrpError("openstacksdk is not installed", hint="pip install 'ccrp[openstack]'") from None
    from openstack.exceptions import ConfigException

    try:
        return openstack.connect(cloud=cloud)
    except ConfigException as exc:
        raise CcrpError(f"cloud {cloud!r} is not configured: {errors.message_of(exc)}",
                        hint="add it to clouds.yaml (or set OS_CLOUD / OS_CLIENT_CONFIG_FILE)") from None


class OpenStackClient:
    backoff = Backoff()
    poll_interval = 2.0  # seconds between status checks of a booting server / saving image
    boot_timeout = 900
    image_timeout = 1800

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        self.inv, self.fleet, self.workdir = inv, inv.fleet, Path(workdir)
        self.settings: OpenStackSettings = inv.provider  # type: ignore[assignment]
        self.conn = _connect(self.settings.cloud)
        self._lock = threading.Lock()
        self._cache: dict[str, object] = {}  # shared lookups (network, flavor...) for parallel clones

    def operator_key(self) -> str:
        """The fleet's operator public key: the key pair ccrp made holds it (what tells it is ours)."""
        return operator_public_key(self.workdir, self.fleet)

    # -- retries and errors ----------------------------------------------------------------------
    def classify_error(self, exc: BaseException):
        return errors.classify(exc)

    def api(self, what: str, fn, *args, **kwargs):
        """Every SDK call goes through here: retried on throttling / 5xx, classified otherwise."""
        return call(fn, *args, classify=self.classify_error, what=what, backoff=self.backoff, **kwargs)

    def errors(self, what: str):
        """SDK failures leave a public method as one-line CcrpErrors with a hint."""
        return translated(what, lambda w, exc: errors.to_ccrp(w, self.settings.cloud, exc) if errors.is_sdk_error(exc) else None)

    # -- services: the first use discovers versions over HTTP, so it is an API call too ---------
    @property
    def compute(self):
        return self.api("compute service discovery", getattr, self.conn, "compute")

    @property
    def network(self):
        return self.api("network service discovery", getattr, self.conn, "network")

    @property
    def image(self):
        return self.api("image service discovery", getattr, self.conn, "image")

    # -- names, tags, listings ------------------------------------------------------------------
    def name(self, *parts: str) -> str:
        return "-".join(("ccrp", self.fleet, *parts))

    def server_name(self, robot: str, role: str = "clone") -> str:
        return self.name("cri" if role == "clone" else role, robot)

    def tags(self, role: str, robot: str | None = None) -> list[str]:
        return [f"{k}={v}" for k, v in owner_labels(self.fleet, role, robot).items()]

    def cached(self, key: str, make):
        with self._lock:
            if key not in self._cache:
                self._cache[key] = make()
            return self._cache[key]

    def remember(self, **values) -> None:
        with self._lock:
            self._cache.update(values)

    def forget_cached(self) -> None:
        with self._lock:
            self._cache.clear()

    def create_tagged(self, what: str, fn, delete, tags: list[str], **attrs):
        """A Neutron resource created with ccrp's ownership tags. Neutron takes `tags` in the POST
        body only with its `tag-creation` extension (2023.1 on). Zed's (scripts/openstack.sh's cloud)
        answers 400 "Attribute 'tags' not allowed in POST" for networks, subnets, routers, security
        groups and floating IPs, and for a port accepts the POST and drops the tags (201, `tags: []`).
        Either way the resource is tagged at once (PUT .../tags, the `standard-attr-tag` extension);
        one that could not be tagged is deleted again, since no listing by tag would ever find it."""
        from openstack.exceptions import BadRequestException

        if not self._cache.get("no-tag-creation"):
            def post():
                try:
                    return fn(tags=tags, **attrs)
                except BadRequestException as exc:
                    if "'tags' not allowed in POST" not in str(exc):
                        raise
                    return None
            res = self.api(f"create {what}", post)
            if res is not None and set(tags) <= set(getattr(res, "tags", None) or []):
                return res
            if res is None:
                with self._lock:
                    self._cache["no-tag-creation"] = True
        else:
            res = None
        if res is None:
            res = self.api(f"create {what}", fn, **attrs)
        try:
            self.api(f"tag {what}", self.network.set_tags, res, tags)
        except BaseException:
            try:
                self.api(f"delete untagged {what}", delete, res, ignore_missing=True)
            except Exception:  # noqa: BLE001 - the tagging failure is the one to report
                pass
            raise
        return res

    def listing(self, what: str, fn, **query) -> list:
        """A list call (the SDK returns a lazy generator: the requests happen inside api())."""
        return self.api(f"list {what}", lambda: list(fn(**query)))

    def tagged(self, collection: str, role: str | None = None, robot: str | None = None) -> list:
        """Neutron resources carrying this fleet's tags (all of them must match)."""
        tags = [f"{LABEL_MANAGED}=true", f"{LABEL_FLEET}={self.fleet}"]
        tags += [f"{LABEL_ROLE}={role}"] if role else []
        tags += [f"{LABEL_ROBOT}={robot}"] if robot else []
        method = "ips" if collection == "fips" else collection
        return self.listing(collection, getattr(self.network, method), tags=",".join(tags))

    def is_owned(self, labels: dict | None, robot: str | None = None) -> bool:
        labels = labels or {}
        return (labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == self.fleet
                and (robot is None or labels.get(LABEL_ROBOT) == robot))

    def find(self, what: str, fn, name_or_id: str):
        """A find_* call; None when the cloud has no such resource."""
        from openstack.exceptions import NotFoundException

        try:
            return self.api(f"find {what}", fn, name_or_id, ignore_missing=False)
        except NotFoundException:
            return None

    def find_or_fail(self, what: str, name_or_id: str, fn, hint: str):
        found = self.find(what, fn, name_or_id)
        if found is None:
            raise CcrpError(f"{what} {name_or_id!r} not found on cloud {self.settings.cloud!r}", hint=hint)
        return found

    # -- the fleet's servers -----------------------------------------------------------------------
    def servers(self, robot: str | None = None) -> list:
        """This fleet's servers: Nova has no idempotency token, so name AND metadata identify them."""
        # Nova filters names by regex on its side: one robot's lookup lists that robot's servers
        # only, not the whole fleet (which made `fleet up` of N clones read N² servers).
        pattern = f"^{self.name()}-" + ("" if robot is None else f"[a-z]+-{robot}$")
        found = self.listing("servers", self.compute.servers, name=pattern)
        return [s for s in found if re.search(pattern, s.name) and self.is_owned(s.metadata, robot)]

    def server(self, robot: str, role: str | None = None):
        found = [s for s in self.servers(robot) if role is None or s.metadata.get(LABEL_ROLE) == role]
        if len(found) > 1:
            raise CcrpError(f"robot {robot!r} has {len(found)} servers on cloud {self.settings.cloud!r}",
                            hint=f"delete the extra ones: `ccrp clone delete --robot {robot}` then recreate")
        return found[0] if found else None

    def running_server(self, robot: str):
        server = self.server(robot)
        if server is None:
            raise CcrpError(f"robot {robot!r} has no clone on cloud {self.settings.cloud!r}",
                            hint=f"ccrp clone create --robot {robot}")
        return server

    def delete_server(self, server) -> None:
        """Delete a server (a Server or an id) and wait until Nova has let go of its port."""
        from openstack.compute.v2.server import Server

        server_id = getattr(server, "id", server)
        self.api("delete server", self.compute.delete_server, server_id, ignore_missing=True)
        self.api("wait for deletion", self.compute.wait_for_delete, Server(id=server_id),
                 interval=self.poll_interval, wait=self.boot_timeout)
