"""The libvirt backend's client: the connection to the libvirt host of `provider.uri`, the fleet's
names, the calls wrapped by retry.call with libvirt's errors classified and translated, and the
lookups every other module of the backend makes (the storage pool and its volumes, networks, the
fleet's domains). Every file the backend makes lives in one storage pool as a volume; every name
starts with `ccrp-<fleet>-`; domains carry the fleet's labels in their metadata (xmldefs.py)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from ...errors import CcrpError, translated
from ...models.inventory import Inventory
from ...retry import Backoff, ErrorClass, call
from ..base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE
from . import xmldefs
from .settings import LOCAL_URIS, URI_PARAMS_ENV, LibvirtSettings, connect_uri

if TYPE_CHECKING:
    from ..docker.client import DockerHost


def _sdk():
    try:
        import libvirt
    except ImportError:
        raise CcrpError("the libvirt Python binding is not installed",
                        hint="pip install 'ccrp[libvirt]' (it builds against libvirt-dev: scripts/libvirt.sh)") from None
    # libvirt prints every error on stderr by default; ours become one-line CcrpErrors instead.
    libvirt.registerErrorHandler(lambda _ctx, _err: None, None)
    return libvirt


def transient(message: str, rpc: bool = False) -> bool:
    """libvirt's answers worth another try: a dropped RPC connection; a pool refreshed while a volume
    is written ("asynchronous jobs running"); a domain start that failed on a cgroup file gone
    ("Unable to read from / write to '.../sys/fs/cgroup/...'"). The last was met in CI: where Docker
    containers with systemd run beside libvirtd, the host's mount table also lists their cgroup mounts,
    libvirtd may pick one of those for a new domain, and it vanishes with its container. The next
    start looks again. Anything else is libvirt's real answer."""
    return rpc or "asynchronous jobs running" in message or (
        message.startswith(("Unable to read from", "Unable to write to")) and "/sys/fs/cgroup/" in message)


# About 40 s in all (full jitter, 2 s at most between tries) for a pool busy writing a volume.
POOL_BUSY = Backoff(attempts=40, base=0.25, cap=2.0)


class LibvirtClient:
    backoff = Backoff()

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        self.inv, self.fleet, self.workdir = inv, inv.fleet, Path(workdir)
        self.settings: LibvirtSettings = inv.provider  # type: ignore[assignment]
        self.libvirt = _sdk()
        # The operator's own URI parameters (an ssh wrapper...) come from the environment, never
        # from the inventory (settings.py).
        uri = connect_uri(self.settings.uri, os.environ)
        try:
            self.conn = self.libvirt.open(uri)
        except self.libvirt.libvirtError as exc:
            raise CcrpError(f"cannot connect to libvirt at {uri}: {self.message(exc)}",
                            hint="start libvirtd (scripts/libvirt.sh) or check provider.uri" +
                                 (f" and {URI_PARAMS_ENV}" if uri != self.settings.uri else "")) from None

    # -- errors and retries ------------------------------------------------------------------
    def message(self, exc: BaseException) -> str:
        text = exc.get_error_message() if hasattr(exc, "get_error_message") else str(exc)
        return " ".join(str(text or exc).split())[:300]

    def classify_error(self, exc: BaseException) -> ErrorClass:
        if isinstance(exc, self.libvirt.libvirtError):
            rpc = exc.get_error_code() == self.libvirt.VIR_ERR_RPC
            return ErrorClass.RETRYABLE if transient(self.message(exc), rpc) else ErrorClass.FATAL
        return ErrorClass.FATAL

    def api(self, what: str, fn, *args, **kwargs):
        """Every libvirt call that changes something goes through here: retried when worth it."""
        return call(fn, *args, classify=self.classify_error, what=what, backoff=self.backoff, **kwargs)

    def missing(self, exc: BaseException, *codes: str) -> bool:
        return isinstance(exc, self.libvirt.libvirtError) and exc.get_error_code() in {
            getattr(self.libvirt, c) for c in codes}

    def errors(self, what: str):
        return translated(what, lambda w, exc: CcrpError(f"{w}: {self.message(exc)}") if isinstance(exc, self.libvirt.libvirtError) else None)

    # -- names ---------------------------------------------------------------------------------
    def name(self, *parts: str) -> str:
        return "-".join(("ccrp", self.fleet, *parts))

    @property
    def public_net(self) -> str:
        return self.name("public")

    @property
    def common_net(self) -> str:
        return self.name("common")

    def domain_name(self, robot: str) -> str:
        return self.name("cri", robot)

    def clone_volumes(self, robot: str) -> dict[str, str]:
        base = self.domain_name(robot)
        return {"disk": f"{base}.qcow2", "seed": f"{base}-seed.iso", "console": f"{base}{xmldefs.CONSOLE_SUFFIX}"}

    def macs(self, robot: str) -> tuple[str, str]:
        return (xmldefs.mac_address(self.fleet, robot, "public"), xmldefs.mac_address(self.fleet, robot, "common"))

    def owns_name(self, name: str) -> bool:
        return name.startswith(self.name() + "-")

    def is_owned(self, labels: dict[str, str], robot: str | None = None) -> bool:
        return (labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == self.fleet
                and (robot is None or labels.get(LABEL_ROBOT) == robot))

    @property
    def local(self) -> bool:
        """The libvirt host is this machine (its firewall, its Docker engine are ours to use)."""
        return self.settings.uri in LOCAL_URIS

    # -- storage -------------------------------------------------------------------------------
    def pool(self, create: bool = False):
        try:
            pool = self.api("look up the storage pool", self.conn.storagePoolLookupByName, self.settings.pool)
        except self.libvirt.libvirtError as exc:
            if not create or not self.missing(exc, "VIR_ERR_NO_STORAGE_POOL"):
                raise
            pool = self.api("define the storage pool", self.conn.storagePoolDefineXML,
                            xmldefs.dir_pool(self.settings.pool, self.settings.pool_dir), 0)
            self.api("build the storage pool", pool.build, 0)
            pool.setAutostart(1)
        if not pool.isActive():
            if not create:
                raise CcrpError(f"storage pool {self.settings.pool} is not active", hint="run `ccrp fleet up`")
            self.api("start the storage pool", pool.create, 0)
        return pool

    def pool_if_active(self):
        """The storage pool, refreshed (its free space and volumes' allocations as they are now), or
        None when it does not exist or is stopped."""
        try:
            pool = self.api("look up the storage pool", self.conn.storagePoolLookupByName, self.settings.pool)
        except self.libvirt.libvirtError as exc:
            if self.missing(exc, "VIR_ERR_NO_STORAGE_POOL"):
                return None
            raise
        return self.refreshed(pool) if pool.isActive() else None

    def vol(self, pool, name: str):
        try:
            return pool.storageVolLookupByName(name)
        except self.libvirt.libvirtError as exc:
            if self.missing(exc, "VIR_ERR_NO_STORAGE_VOL"):
                return None
            raise

    def refreshed(self, pool):
        """The pool, refreshed. libvirt refuses while another of the fleet's volumes is being
        written (a clone's disk, a golden upload: "asynchronous jobs running"), which under load
        lasts longer than a throttled call's retries: its own patience, whatever `backoff` says
        (CI: 20 attempts of the contract harness's fast backoff ran out in a storm of creates)."""
        call(pool.refresh, 0, classify=self.classify_error, what="refresh the storage pool", backoff=POOL_BUSY)
        return pool

    def upload(self, pool, name: str, data: bytes | Path, fmt: str, capacity: int | None = None):
        """A new volume holding `data` (bytes, or a local file streamed in pieces) through libvirt's
        stream API, so the libvirt host may be another machine."""
        size = len(data) if isinstance(data, bytes) else Path(data).stat().st_size
        vol = self.api(f"create volume {name}", pool.createXML, xmldefs.volume(name, capacity or size, fmt), 0)
        try:
            stream = self.conn.newStream(0)
            vol.upload(stream, 0, size, 0)
            if isinstance(data, bytes):
                view = memoryview(data)
                sent = 0
                while sent < size:
                    sent += stream.send(bytes(view[sent:sent + (1 << 20)]))
            else:
                with open(data, "rb") as fh:
                    stream.sendAll(lambda _s, n, f: f.read(n), fh)
            stream.finish()
        except BaseException:
            vol.delete(0)
            raise
        return vol

    def download(self, vol, offset: int = 0) -> bytes:
        chunks: list[bytes] = []
        stream = self.conn.newStream(0)
        vol.download(stream, offset, 0, 0)
        stream.recvAll(lambda _s, buf, _o: chunks.append(buf), None)
        stream.finish()
        return b"".join(chunks)

    def delete_vol(self, pool, name: str) -> bool:
        vol = self.vol(pool, name)
        if vol is None:
            return False
        self.api(f"delete volume {name}", vol.delete, 0)
        return True

    # -- networks and domains --------------------------------------------------------------------
    def network(self, name: str):
        try:
            return self.conn.networkLookupByName(name)
        except self.libvirt.libvirtError as exc:
            if self.missing(exc, "VIR_ERR_NO_NETWORK"):
                return None
            raise

    def domains(self, robot: str | None = None, role: str | None = None) -> list:
        """This fleet's domains: name prefix AND metadata labels. One undefined between the listing and
        the read (a robot's rollback in a parallel `fleet up`) is gone, not an error."""
        found = []
        for dom in self.conn.listAllDomains(0):
            if not self.owns_name(dom.name()):
                continue
            try:
                info = xmldefs.domain_info(dom.XMLDesc(0))
            except self.libvirt.libvirtError as exc:
                if self.missing(exc, "VIR_ERR_NO_DOMAIN"):
                    continue
                raise
            if self.is_owned(info.labels, robot) and (role is None or info.labels.get(LABEL_ROLE) == role):
                found.append((dom, info))
        return found

    def domain(self, robot: str):
        found = self.domains(robot, "clone")
        return found[0] if found else (None, None)

    _docker: DockerHost | bool | None = None  # this host's Docker engine, once asked (False: none, or the libvirt host is elsewhere)

    def docker_host(self):
        """This host's Docker engine when simulated robots of the fleet can be on it (a local URI):
        `fleet down` and `gc` remove them with the network they sit on."""
        if self._docker is None:
            self._docker = False
            if self.local:
                from ..docker.client import DockerHost

                try:
                    self._docker = DockerHost(self.fleet)
                except CcrpError:  # no engine, so no simulated robot either
                    pass
        return self._docker or None

    def close(self) -> None:
        try:
            self.conn.close()
        except self.libvirt.libvirtError:
            pass
