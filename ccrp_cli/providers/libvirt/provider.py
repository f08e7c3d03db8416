"""libvirt provider: a clone is a VM on the libvirt host of `provider.uri` (qemu:///system by
default; a remote host over qemu+ssh:// as libvirt supports it). Its disk is a qcow2 overlay backed
by the fleet's golden volume (copy-on-write: a clone's disk costs only its writes), it boots the
golden volume's kernel and initramfs directly, and cloud-init reads a NoCloud seed (an ISO volume)
with the user-data ccrp renders for the clouds. Its public side is the fleet's NAT network (the
host reaches it; its address is a DHCP lease), its common side an isolated network with the static
address of the addressing plan. Transport is SSH with host keys pinned from the serial console,
which virtlogd writes into the storage pool (read back through libvirt, so remote hosts work too).

Every file the provider makes lives in one storage pool as a volume; every name starts with
`ccrp-<fleet>-`. Domains carry the fleet's labels in their metadata (xmldefs.py)."""

from __future__ import annotations

import datetime as dt
import json
import os
import re
import threading
import time
from collections.abc import Sequence
from contextlib import contextmanager
from pathlib import Path

from ...errors import CcrpError
from ...models.inventory import Inventory
from ...retry import ErrorClass
from ..base import (LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE, CloneRecord, CloneSpec, CloneState, Origin,
                    OwnedResource, Quota, RobotAttachment, Role, SnapshotRecord, owner_labels, with_roles)
from ..cloud import CloudProvider
from . import INFO, forward, robots, seed, xmldefs
from .settings import URI_PARAMS_ENV, LibvirtSettings, connect_uri

# virDomainState (dom.state()[0]) -> libvirt's word, then ccrp's.
WORDS = ("nostate", "running", "blocked", "paused", "shutdown", "shutoff", "crashed", "pmsuspended")
STATES = {"nostate": CloneState.PENDING, "running": CloneState.RUNNING, "blocked": CloneState.RUNNING,
          "paused": CloneState.STOPPED, "shutdown": CloneState.STOPPING, "shutoff": CloneState.STOPPED,
          "crashed": CloneState.ERROR, "pmsuspended": CloneState.STOPPED}
GOLDEN = re.compile(r"^ccrp-(?P<fleet>[a-z][a-z0-9]*)-golden-(?:(?P<robot>[a-z][a-z0-9]*)-)?(?P<stamp>\d{14})\.qcow2$")
# A clone's volumes after `ccrp-<fleet>-cri-`: its robot, then what it is (LibvirtProvider.clone_volumes).
CLONE_VOLUME = re.compile(r"^(?P<robot>[a-z][a-z0-9]*)(\.qcow2|-seed\.iso|\.console)$")
# A clone's overlay of any fleet (the pool is shared): the disk quota holds what each may still take.
OVERLAY = re.compile(r"^ccrp-[a-z][a-z0-9]*-cri-[a-z][a-z0-9]*\.qcow2$")
CONSOLE_TAIL = 4 << 20  # bytes of a console log read at most (its last boots)
PROBE_MARK = re.compile(r"Run /init as init process|Freeing unused kernel")
PROBE_TIMEOUT = 20.0
# Setting a clone's clock (sync_clock): rounds at most, and what is close enough to the host's.
CLOCK_ROUNDS, CLOCK_TOLERANCE = 4, 0.005
# Waits on an emulated (TCG) guest get this many times the time ccrp's callers give a VM: its first
# boot took 272 s to the end of cloud-init on this 2-core machine under load (docs/libvirt.md),
# where `fleet up` gives a clone 300 s, and every command in it runs several times slower.
TCG_SLOWDOWN = 3  # a guest that works gets there in about a second under KVM, two under TCG
PRESS_AGAIN, PRESS_FOR = 10, 60  # s: stop_instance's power button presses (PRESS_FOR times the above)


def _sdk():
    try:
        import libvirt
    except ImportError:
        raise CcrpError("the libvirt Python binding is not installed",
                        hint="pip install 'ccrp[libvirt]' (it builds against libvirt-dev: scripts/libvirt.sh)") from None
    # libvirt prints every error on stderr by default; ours become one-line CcrpErrors instead.
    libvirt.registerErrorHandler(lambda _ctx, _err: None, None)
    return libvirt


def _listening(host: str, port: int = 22) -> bool:
    import socket

    try:
        socket.create_connection((host, port), timeout=2).close()
        return True
    except OSError:
        return False


# What each kind is to the fleet (`ccrp gc`); volumes and port forwards belong to a robot.
ROLES = {"instance": Role.CLONE, "robot_sim": Role.ROBOT_SIDE, "image": Role.IMAGE, "network": Role.BOOTSTRAP}
SHOWN_KINDS = {"instance": "domain", "robot_sim": "container", "port_forward": "port forward"}  # as `fleet down` reports them


def _shown(r: OwnedResource) -> str:
    return f"{SHOWN_KINDS.get(r.kind, r.kind)} {r.name or r.id}"


def stamp() -> str:
    return dt.datetime.now(dt.timezone.utc).strftime("%Y%m%d%H%M%S")


class LibvirtProvider(CloudProvider):
    kind = "libvirt"
    abilities = INFO.abilities
    # VMs boot on the libvirt host's CPUs (emulated ones, under TCG): a few at a time.
    max_parallel = 4
    boot_timeout = 900

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        super().__init__(inv, workdir)
        self.settings: LibvirtSettings = inv.provider  # type: ignore[assignment]
        self.libvirt = _sdk()
        # The operator's own URI parameters (an ssh wrapper...) come from the environment, never
        # from the inventory (settings.py).
        uri = connect_uri(self.settings.uri, os.environ)
        try:
            self.conn = self.libvirt.open(uri)
        except self.libvirt.libvirtError as exc:
            raise CcrpError(f"cannot connect to libvirt at {uri}: {self._message(exc)}",
                            hint="start libvirtd (scripts/libvirt.sh) or check provider.uri" +
                                 (f" and {URI_PARAMS_ENV}" if uri != self.settings.uri else "")) from None
        self._lock = threading.Lock()
        self._accel: str | None = None
        self._emulated: dict[str, bool] = {}  # robot -> its domain runs under TCG

    # -- errors ------------------------------------------------------------------------------
    def _message(self, exc: BaseException) -> str:
        text = exc.get_error_message() if hasattr(exc, "get_error_message") else str(exc)
        return " ".join(str(text or exc).split())[:300]

    def classify_error(self, exc: BaseException) -> ErrorClass:
        # A pool refreshed while a volume is being written ("asynchronous jobs running") and a
        # dropped RPC connection are worth another try; anything else is libvirt's real answer.
        if isinstance(exc, self.libvirt.libvirtError):
            text = self._message(exc)
            if "asynchronous jobs running" in text or exc.get_error_code() == self.libvirt.VIR_ERR_RPC:
                return ErrorClass.RETRYABLE
        return ErrorClass.FATAL

    def _missing(self, exc: BaseException, *codes: str) -> bool:
        return isinstance(exc, self.libvirt.libvirtError) and exc.get_error_code() in {
            getattr(self.libvirt, c) for c in codes}

    @contextmanager
    def _errors(self, what: str):
        try:
            yield
        except self.libvirt.libvirtError as exc:
            raise CcrpError(f"{what}: {self._message(exc)}") from exc

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

    def _owns_name(self, name: str) -> bool:
        return name.startswith(self.name() + "-")

    def _is_owned(self, labels: dict[str, str], robot: str | None = None) -> bool:
        return (labels.get(LABEL_MANAGED) == "true" and labels.get(LABEL_FLEET) == self.fleet
                and (robot is None or labels.get(LABEL_ROBOT) == robot))

    # -- storage -------------------------------------------------------------------------------
    def _pool(self, create: bool = False):
        try:
            pool = self.api("look up the storage pool", self.conn.storagePoolLookupByName, self.settings.pool)
        except self.libvirt.libvirtError as exc:
            if not create or not self._missing(exc, "VIR_ERR_NO_STORAGE_POOL"):
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

    def _vol(self, pool, name: str):
        try:
            return pool.storageVolLookupByName(name)
        except self.libvirt.libvirtError as exc:
            if self._missing(exc, "VIR_ERR_NO_STORAGE_VOL"):
                return None
            raise

    def _refreshed(self, pool):
        self.api("refresh the storage pool", pool.refresh, 0)
        return pool

    def _upload(self, pool, name: str, data: bytes | Path, fmt: str, capacity: int | None = None):
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

    def _download(self, vol, offset: int = 0) -> bytes:
        chunks: list[bytes] = []
        stream = self.conn.newStream(0)
        vol.download(stream, offset, 0, 0)
        stream.recvAll(lambda _s, buf, _o: chunks.append(buf), None)
        stream.finish()
        return b"".join(chunks)

    def _delete_vol(self, pool, name: str) -> bool:
        vol = self._vol(pool, name)
        if vol is None:
            return False
        self.api(f"delete volume {name}", vol.delete, 0)
        return True

    # -- networks ------------------------------------------------------------------------------
    def _network(self, name: str):
        try:
            return self.conn.networkLookupByName(name)
        except self.libvirt.libvirtError as exc:
            if self._missing(exc, "VIR_ERR_NO_NETWORK"):
                return None
            raise

    def bootstrap(self) -> None:
        """The storage pool (shared by fleets), the fleet's NAT and isolated networks: created or
        reused, started, set to autostart."""
        public = self.settings.public_cidr
        for what, cidr in (("common.cidr", self.inv.common.cidr), ("vpn.pool", self.inv.vpn.pool)):
            if public.overlaps(cidr):
                raise CcrpError(f"provider.public_cidr {public} overlaps {what} {cidr}", hint="change one of them")
        if self.settings.vpn_forward is not None:
            self._check_forward_address(str(self.settings.vpn_forward.address))
        # The operator key before clones are made in parallel: each would otherwise make its own when
        # there is none, the last one written wins, and the others' clones refuse it (measured).
        self.operator_public_key()
        with self._errors(f"bootstrap of fleet {self.fleet}"):
            self._pool(create=True)
            for name, xml in ((self.public_net, xmldefs.nat_network(self.public_net, xmldefs.bridge_name(self.fleet, "public"), public)),
                              (self.common_net, xmldefs.isolated_network(self.common_net, xmldefs.bridge_name(self.fleet, "common")))):
                net, defined = self._network(name), False
                try:
                    if net is None:
                        net, defined = self.api(f"define network {name}", self.conn.networkDefineXML, xml), True
                    if not net.isActive():
                        self.api(f"start network {name}", net.create)
                except self.libvirt.libvirtError as exc:
                    if defined:  # a network that cannot start ("already in use by interface ...") goes again
                        net.undefine()
                    raise CcrpError(f"cannot set up libvirt network {name}: {self._message(exc)}",
                                    hint="another network uses that range: change provider.public_cidr") from None
                net.setAutostart(1)

    # -- acceleration ---------------------------------------------------------------------------
    @property
    def _accel_cache(self) -> Path:
        return self.workdir / "libvirt-accel.json"

    def _probed(self) -> dict[str, str]:
        try:
            cached = json.loads(self._accel_cache.read_text())
        except (OSError, ValueError):
            return {}
        return cached if isinstance(cached, dict) else {}

    def accel(self, kernel: str, initrd: str) -> str:
        """kvm or tcg: the inventory's choice, else what a probe boot found on this host (kept in the
        fleet store per URI, so the probe runs once; delete libvirt-accel.json to probe again)."""
        if self.settings.accel != "auto":
            return self.settings.accel
        with self._lock:
            if self._accel:
                return self._accel
            cached = self._probed()
            if cached.get(self.settings.uri) not in ("kvm", "tcg"):
                from ...store import atomic_write

                cached[self.settings.uri], why = self.probe_kvm(kernel, initrd)
                cached[f"{self.settings.uri} why"] = why
                atomic_write(self._accel_cache, json.dumps(cached) + "\n")
            self._accel = cached[self.settings.uri]
            return self._accel

    def probe_kvm(self, kernel: str, initrd: str) -> tuple[str, str]:
        """("kvm" | "tcg", why): boot a disk-less KVM guest with the golden kernel and wait for it to
        start its initramfs. A /dev/kvm that opens is not enough: without vmx/svm a guest hangs
        early or QEMU aborts setting an MSR (docs/libvirt.md)."""
        try:
            self.conn.getDomainCapabilities(None, "x86_64", None, "kvm", 0)
        except self.libvirt.libvirtError as exc:
            return "tcg", f"libvirt offers no KVM here ({self._message(exc)[:120]})"
        pool = self._pool()
        log_name = self.name("kvm-probe") + xmldefs.CONSOLE_SUFFIX
        log_path = f"{xmldefs.pool_path(pool.XMLDesc(0))}/{log_name}"
        t0, seen, dom = time.monotonic(), "", None
        try:  # virtlogd writes the log even for a guest QEMU could not start: it goes in any case
            try:
                dom = self.conn.createXML(xmldefs.probe_domain(self.name("kvm-probe"), kernel, initrd, log_path), 0)
            except self.libvirt.libvirtError as exc:
                # QEMU's own line says why ("failed to set MSR 0x10a to 0x69" without vmx/svm), after libvirt's words.
                said = self._message(exc).split("qemu-system-x86_64: ")
                why = next((part for part in said if part.startswith("error: ")), said[-1])
                return "tcg", f"a KVM guest did not start ({why.strip()[:160]})"
            while time.monotonic() - t0 < PROBE_TIMEOUT:
                vol = self._vol(self._refreshed(pool), log_name)
                seen = self._download(vol).decode(errors="replace") if vol is not None else ""
                if PROBE_MARK.search(seen):
                    return "kvm", f"a KVM guest started its initramfs in {time.monotonic() - t0:.1f} s"
                if not dom.isActive():
                    break
                time.sleep(0.5)
        finally:
            if dom is not None:
                try:
                    dom.destroy()
                except self.libvirt.libvirtError:
                    pass  # ended by itself (panic=-1, on_reboot destroy)
            self._delete_vol(self._refreshed(pool), log_name)
        return "tcg", f"a KVM guest did not reach its initramfs in {PROBE_TIMEOUT:.0f} s ({seen.strip()[-80:]!r})"

    # -- clones ---------------------------------------------------------------------------------
    def _domains(self, robot: str | None = None, role: str | None = None) -> list:
        """This fleet's domains: name prefix AND metadata labels. One undefined between the listing and
        the read (a robot's rollback in a parallel `fleet up`) is gone, not an error."""
        found = []
        for dom in self.conn.listAllDomains(0):
            if not self._owns_name(dom.name()):
                continue
            try:
                info = xmldefs.domain_info(dom.XMLDesc(0))
            except self.libvirt.libvirtError as exc:
                if self._missing(exc, "VIR_ERR_NO_DOMAIN"):
                    continue
                raise
            if self._is_owned(info.labels, robot) and (role is None or info.labels.get(LABEL_ROLE) == role):
                found.append((dom, info))
        return found

    def _domain(self, robot: str):
        found = self._domains(robot, "clone")
        return found[0] if found else (None, None)

    def _offset(self, common_ip: str) -> int:
        """The clone's place in the addressing plan: its common address's offset in common.cidr."""
        import ipaddress

        pub = self.settings.public_cidr
        offset = int(ipaddress.IPv4Address(common_ip)) - int(self.inv.common.cidr.network_address)
        hosts = pub.num_addresses - 2 - len(xmldefs.robot_block(pub))
        if not 2 <= offset <= hosts:  # .1 is the host's, the top the simulated robots'
            raise CcrpError(f"clone address {common_ip} has no counterpart in provider.public_cidr {pub}",
                            hint="give provider.public_cidr at least as many addresses as common.cidr")
        return offset

    def public_ip(self, common_ip: str) -> str:
        """The clone's public address: at its common address's offset in provider.public_cidr (the
        addressing plan gives each clone its own), reserved for its MAC on the NAT network."""
        return str(self.settings.public_cidr.network_address + self._offset(common_ip))

    # -- robots outside the host (provider.vpn_forward, forward.py) --------------------------------
    def _forward(self, robot: str, common_ip: str | None) -> forward.Forward | None:
        fwd = self.settings.vpn_forward
        if fwd is None or not common_ip:
            return None
        return forward.Forward(self.fleet, robot, str(fwd.address), fwd.base_port + self._offset(common_ip),
                               self.public_ip(common_ip), self.inv.vpn.port, self.inv.vpn.proto)

    @staticmethod
    def _check_forward_address(address: str) -> None:
        """vpn_forward.address must be this machine's: robots' packets to it are the ones forwarded."""
        import socket

        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            try:
                sock.bind((address, 0))
            except OSError:
                raise CcrpError(f"provider.vpn_forward.address {address} is not an address of this machine",
                                hint="give the libvirt host's address on the robots' LAN (`ip -4 address`)") from None

    def _forwards(self) -> list[OwnedResource]:
        """The fleet's port forwards, one per robot. Listed only where they can be (this machine's
        firewall, root): with vpn_forward unset, a forward left by an earlier inventory is still found."""
        if self.settings.uri not in robots.LOCAL_URIS:
            return []
        try:
            rules = forward.listed(self.fleet)
        except CcrpError:
            if self.settings.vpn_forward is not None:
                raise
            return []
        robots_seen = sorted({forward.robot_of(spec) for _table, spec in rules})
        return [OwnedResource(kind="port_forward", id=forward.comment(self.fleet, r), name=forward.comment(self.fleet, r), robot=r)
                for r in robots_seen]

    def _reserve(self, mac: str, ip: str, hostname: str) -> None:
        net = self._network(self.public_net)
        if net is None:
            raise CcrpError(f"fleet {self.fleet!r} has no network {self.public_net}", hint="run `ccrp fleet up`")
        have = xmldefs.dhcp_hosts(net.XMLDesc(0))
        if have.get(mac) == ip:
            return
        lv, flags = self.libvirt, self.libvirt.VIR_NETWORK_UPDATE_AFFECT_CONFIG
        flags |= lv.VIR_NETWORK_UPDATE_AFFECT_LIVE if net.isActive() else 0
        if mac in have:
            self._unreserve(mac)
        self.api("reserve the public address", net.update, lv.VIR_NETWORK_UPDATE_COMMAND_ADD_LAST,
                 lv.VIR_NETWORK_SECTION_IP_DHCP_HOST, -1, xmldefs.dhcp_host(mac, ip, hostname), flags)

    def _unreserve(self, mac: str) -> None:
        net = self._network(self.public_net)
        if net is None or mac not in (have := xmldefs.dhcp_hosts(net.XMLDesc(0))):
            return
        lv, flags = self.libvirt, self.libvirt.VIR_NETWORK_UPDATE_AFFECT_CONFIG
        flags |= lv.VIR_NETWORK_UPDATE_AFFECT_LIVE if net.isActive() else 0
        self.api("release the public address", net.update, lv.VIR_NETWORK_UPDATE_COMMAND_DELETE,
                 lv.VIR_NETWORK_SECTION_IP_DHCP_HOST, -1, xmldefs.dhcp_host(mac, have[mac]), flags)

    def _reserved(self, mac: str) -> str | None:
        net = self._network(self.public_net)
        return xmldefs.dhcp_hosts(net.XMLDesc(0)).get(mac) if net is not None else None

    # -- simulated robots (Ability.ROBOT_ATTACH, robots.py) ----------------------------------------
    def attach_robot(self, robot: str, index: int) -> RobotAttachment:
        """On no Docker network: its port on the fleet's NAT network is its only interface."""
        port = self.robot_port(robot, index)
        return RobotAttachment(network="none", name=port.network, address=str(port.address.ip), attach=port.attach)

    def detach_robot(self, robot: str) -> None:
        self.release_robot_port(robot)

    def robot_port(self, robot: str, index: int) -> robots.RobotPort:
        """The port of robot `robot` (addressing slot `index`) on the fleet's NAT network: refused
        in one line unless the libvirt host is this machine or the network is missing."""
        import ipaddress

        robots.require_local(self.settings.uri)
        with self._errors(f"network {self.public_net}"):
            net = self._network(self.public_net)
            if net is None or not net.isActive():
                raise CcrpError(f"fleet {self.fleet!r} has no running network {self.public_net}", hint="run `ccrp fleet up`")
            taken = set(xmldefs.dhcp_hosts(net.XMLDesc(0)).values())
            taken |= {lease.get("ipaddr", "") for lease in net.DHCPLeases()}
            bridge = net.bridgeName()
        cidr = self.settings.public_cidr
        address = robots.robot_address(cidr, index, taken, robot)
        return robots.RobotPort(network=self.public_net, bridge=bridge, veth=robots.veth_name(self.fleet, robot),
                                address=ipaddress.IPv4Interface(f"{address}/{cidr.prefixlen}"))

    def release_robot_port(self, robot: str) -> None:
        if self.settings.uri in robots.LOCAL_URIS:
            robots.release(self.fleet, robot)

    _docker = None  # this host's Docker engine, once asked (False: none, or the libvirt host is elsewhere)

    def _sim_host(self):
        """This host's Docker engine when simulated robots of the fleet can be on it (a local URI):
        `fleet down` and `gc` remove them with the network they sit on."""
        if self._docker is None:
            self._docker = False
            if self.settings.uri in robots.LOCAL_URIS:
                from ..docker.host import DockerHost

                try:
                    self._docker = DockerHost(self.fleet)
                except CcrpError:  # no engine, so no simulated robot either
                    pass
        return self._docker or None

    def _sims(self) -> list:
        """The fleet's simulated robots and power devices (containers labelled with its name)."""
        host = self._sim_host()
        if host is None:
            return []
        return [c for c in host.client.containers.list(all=True, ignore_removed=True,
                                                       filters={"label": [f"{LABEL_FLEET}={self.fleet}"]})
                if c.labels.get(LABEL_ROLE) in ("robot-sim", "power-sim")]

    def _record(self, dom, info: xmldefs.DomainInfo, origin: Origin | None = None) -> CloneRecord:
        word = WORDS[dom.state(0)[0]] if dom.state(0)[0] < len(WORDS) else "unknown"
        mac = info.macs.get(self.public_net)
        robot = info.labels.get(LABEL_ROBOT, "")
        fw = self._forward(robot, info.common_ip)
        return CloneRecord(robot=robot, provider_id=dom.UUIDString(),
                           state=CloneState.of(word, STATES), status=word,
                           public_ip=self._reserved(mac) if mac else None, common_ip=info.common_ip, origin=origin,
                           endpoint=fw.endpoint if fw else None)

    def query(self) -> dict[str, CloneRecord]:
        with self._errors("list clones"):
            return {r.robot: r for r in (self._record(d, i) for d, i in self._domains(role="clone"))}

    def golden(self, image: str) -> tuple[str, str, str]:
        """The golden volume's path, and its kernel's and initramfs's (volumes beside it)."""
        pool = self._pool()
        stem = image.removesuffix(".qcow2")
        vols = [self._vol(pool, n) for n in (image, f"{stem}.vmlinuz", f"{stem}.initrd")]
        if not image.endswith(".qcow2") or any(v is None for v in vols):
            raise CcrpError(f"golden volume {image} (with its .vmlinuz and .initrd) is not in storage pool {self.settings.pool}",
                            hint="import the fleet's snapshot (docs/libvirt.md)")
        return tuple(v.path() for v in vols)  # type: ignore[return-value]

    def timeout_scale(self, robot: str) -> int:
        """TCG_SLOWDOWN for a clone emulated by TCG (its domain type is qemu), else 1."""
        with self._lock:
            known = self._emulated.get(robot)
        if known is None:
            dom, _info = self._domain(robot)
            if dom is None:
                return 1
            import xml.etree.ElementTree as ET

            known = ET.fromstring(dom.XMLDesc(0)).get("type") == "qemu"
            with self._lock:
                self._emulated[robot] = known
        return TCG_SLOWDOWN if known else 1

    def wait_ready(self, robot: str, timeout: float = 600) -> None:
        """As on a cloud, once the clone's sshd listens: the SSH transport's own retries (about 25 s)
        end sooner than a TCG boot gets there. A clone started again has its host keys known already;
        a new one prints them on the console in cloud-init's first stage (goldens.py CLOUD_CFG), and
        sshd starts only after that stage: 25 s after the keys, nao2's sshd was not listening yet in
        one loaded run (load average 5-8)."""
        from ...retry import PollTimeout, poll

        timeout *= self.timeout_scale(robot)
        deadline = time.monotonic() + timeout
        rec = self.query().get(robot)
        if rec is not None and rec.public_ip:
            try:
                poll(lambda: (_listening(rec.public_ip), None), timeout=timeout, interval=2.0)
            except PollTimeout:
                raise CcrpError(f"clone of {robot}: nothing listens on {rec.public_ip}:22 after {timeout:.0f} s",
                                hint=f"ccrp clone exec --robot {robot} -- systemctl status ssh, or read its console") from None
        super().wait_ready(robot, max(1.0, deadline - time.monotonic()))
        self.sync_clock(robot, timeout=max(10.0, deadline - time.monotonic()))

    def sync_clock(self, robot: str, timeout: float = 60) -> float | None:
        """Set the clone's clock to this host's through its guest agent: a VM's clock starts from the
        emulated RTC's whole seconds (goldens.py GUEST_AGENT_RPCS). Returns how far behind the host
        the clone's clock was, in seconds; None when no agent answered within timeout (a clone whose
        domain or golden volume predates the agent keeps the clock it booted with)."""
        dom, _info = self._domain(robot)
        if dom is None or xmldefs.GUEST_AGENT not in dom.XMLDesc(0):
            return None
        deadline = time.monotonic() + timeout
        while True:
            try:
                behind, _rtt = self._clock_behind(dom)
                break
            except self.libvirt.libvirtError:
                # The agent starts with the guest's udev (its port appears) and may not answer yet.
                if time.monotonic() >= deadline:
                    return None
                time.sleep(1.0)
        # The guest applies the time it is sent some milliseconds after the host read it (tens
        # under TCG on a loaded host: 15 and 69 ms behind, measured): each round adds what the
        # clone is still behind by to the next time sent, until that is within the reading's error.
        lead = 0.0
        with self._errors(f"clock of the clone of {robot}"):
            for _ in range(CLOCK_ROUNDS):
                now = time.time_ns() + int(lead * 1e9)
                dom.setTime({"seconds": now // 1_000_000_000, "nseconds": now % 1_000_000_000}, 0)
                still, rtt = self._clock_behind(dom)
                if abs(still) <= max(CLOCK_TOLERANCE, rtt / 2):
                    break
                lead += still
        return behind

    @staticmethod
    def _clock_behind(dom) -> tuple[float, float]:
        """(how far the guest's clock is behind this host's, the reading's round trip), in seconds."""
        before = time.time()
        guest = dom.getTime(0)
        after = time.time()
        return (before + after) / 2 - (guest["seconds"] + guest["nseconds"] / 1e9), after - before

    def has_image(self, image: str) -> bool:
        try:
            self.golden(image)
            return True
        except CcrpError:
            return False

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Define and start the clone's VM, or start the one that exists; roll back only what this
        attempt created."""
        INFO.fit_user_data(spec.user_data)
        fw = self._forward(spec.robot, spec.common_ip)
        if fw is not None:  # before the VM: its first boot is when a robot may first dial
            forward.ensure(fw)
        with self._errors(f"clone of {spec.robot}"):
            dom, info = self._domain(spec.robot)
            if dom is not None:
                state = dom.state(0)[0]
                if state == self.libvirt.VIR_DOMAIN_PAUSED:
                    self.api("resume domain", dom.resume)
                elif not dom.isActive():
                    self.api("start domain", dom.create)
                    return self._record(dom, info, Origin.RESUMED)
                return self._record(dom, info, Origin.REUSED)
            created: list[str] = []
            pool = self._pool()
            try:
                dom = self._define(spec, pool, created)
                self.api("start domain", dom.create)
            except BaseException as exc:
                left = self._rollback(pool, spec.robot, created)
                if fw is not None:
                    forward.remove(self.fleet, spec.robot)
                if left and isinstance(exc, CcrpError):
                    exc.message += f" (rollback left {', '.join(left)}: `ccrp gc` removes them)"
                raise
            return self._record(dom, xmldefs.domain_info(dom.XMLDesc(0)), Origin.CREATED)

    def _define(self, spec: CloneSpec, pool, created: list[str]):
        disk_path, kernel, initrd = self.golden(spec.image)
        vols = self.clone_volumes(spec.robot)
        for stale in vols.values():  # left by an attempt that died before defining its domain
            self._delete_vol(self._refreshed(pool), stale)
        self.create_overlay(pool, vols["disk"], spec.image, disk_path)
        created.append(vols["disk"])
        public_mac, common_mac = self.macs(spec.robot)
        self._reserve(public_mac, self.public_ip(spec.common_ip), spec.hostname)
        iso = seed.seed_iso(spec.user_data, spec.instance_id, spec.hostname,
                            seed.network_config(public_mac, common_mac, spec.common_ip, self.inv.common.cidr))
        self._upload(pool, vols["seed"], iso, "raw")
        created.append(vols["seed"])
        console = f"{xmldefs.pool_path(pool.XMLDesc(0))}/{vols['console']}"
        created.append(vols["console"])  # virtlogd makes it at the first start
        xml = xmldefs.domain(xmldefs.DomainSpec(
            name=self.domain_name(spec.robot), title=f"ccrp clone of robot {spec.robot} (fleet {self.fleet})",
            labels=owner_labels(self.fleet, spec.role, spec.robot), common_ip=spec.common_ip,
            accel=self.accel(kernel, initrd), memory_mb=self.settings.memory_mb, vcpus=self.settings.vcpus,
            pool=self.settings.pool, disk=vols["disk"], seed=vols["seed"], kernel=kernel, initrd=initrd,
            console_log=console,
            nics=(xmldefs.Nic(self.public_net, public_mac), xmldefs.Nic(self.common_net, common_mac))))
        dom = self.api("define domain", self.conn.defineXML, xml)
        created.append(f"domain:{self.domain_name(spec.robot)}")
        return dom

    def create_overlay(self, pool, name: str, image: str, disk_path: str) -> None:
        """A clone's disk: qcow2 volume `name` of golden volume `image`'s virtual size, backed by it
        (at `disk_path`): it holds only the clone's writes (bench/libvirt.py times this)."""
        capacity = pool.storageVolLookupByName(image).info()[1]
        self.api("create the overlay", pool.createXML, xmldefs.volume(name, capacity, "qcow2", backing=disk_path), 0)

    def footprint(self, robot: str) -> dict[str, float]:
        """What the robot's clone takes of the host now: its overlay's allocation on disk (MB) and
        its QEMU process's resident memory (MiB; absent while the domain is off)."""
        with self._errors(f"footprint of {robot}"):
            dom, _info = self._domain(robot)
            vol = self._vol(self._refreshed(self._pool()), self.clone_volumes(robot)["disk"])
            found = {"overlay_mb": round(vol.info()[2] / 1e6, 1)} if vol is not None else {}
            if dom is not None and dom.isActive():
                found["rss_mib"] = round(dom.memoryStats().get("rss", 0) / 1024, 1)
            return found

    def _rollback(self, pool, robot: str, created: list[str]) -> list[str]:
        left = []
        for item in reversed(created):
            try:
                if item.startswith("domain:"):
                    self._remove_domain(robot)
                else:
                    self._delete_vol(self._refreshed(pool), item)
            except Exception:  # noqa: BLE001 - best effort: report, never mask the real failure
                left.append(item)
        return left

    def _remove_domain(self, robot: str) -> bool:
        dom, _info = self._domain(robot)
        if dom is None:
            return False
        if dom.isActive():
            self.api("destroy domain", dom.destroy)
        self.api("undefine domain", dom.undefine)
        return True

    def stop_instance(self, robot: str) -> bool:
        """The ACPI power button: systemd in the clone shuts it down (autostop's poweroff ends the
        same way). Pressed again every PRESS_AGAIN s while the VM runs, for up to PRESS_FOR s (times
        the TCG slowdown): a press before the guest's kernel has loaded its button driver, early in
        its boot, is lost (the contract suite's clones are stopped right after they start). A guest
        still running then does not listen (a hung kernel): its power is cut, as the clouds' stop
        does after its grace period, so that `clone restart` restarts a clone that no longer answers."""
        with self._errors(f"stop clone of {robot}"):
            dom, _info = self._domain(robot)
            if dom is None or dom.state(0)[0] != self.libvirt.VIR_DOMAIN_RUNNING:
                return False
            # paramiko still took the old connection for active after the VM's power-off, and the
            # first command after a restart was reset: closed now.
            self.transport.forget(robot)
            deadline = time.monotonic() + PRESS_FOR * self.timeout_scale(robot)
            while dom.isActive():
                try:
                    self.api("shut down domain", dom.shutdown)
                except self.libvirt.libvirtError:
                    if dom.isActive():
                        raise
                    break  # it powered off between the check and the press
                pressed = time.monotonic()
                while dom.isActive() and time.monotonic() - pressed < PRESS_AGAIN:
                    time.sleep(0.5)
                if time.monotonic() > deadline and dom.isActive():
                    # QEMU ends on SIGTERM (its caches flushed to the overlay), the domain stays defined.
                    self.api("power off domain", dom.destroyFlags, self.libvirt.VIR_DOMAIN_DESTROY_GRACEFUL)
                    break
            return True

    def terminate(self, robot: str) -> bool:
        """The robot's VM and its volumes (overlay, seed, console)."""
        with self._errors(f"delete clone of {robot}"):
            with self._lock:
                self._emulated.pop(robot, None)
            self.transport.forget(robot)
            existed = self._remove_domain(robot)
            self._unreserve(self.macs(robot)[0])
            if any(r.robot == robot for r in self._forwards()):
                forward.remove(self.fleet, robot)
            pool = self._refreshed(self._pool())
            for name in self.clone_volumes(robot).values():
                self._delete_vol(pool, name)
            return existed

    def console_output(self, robot: str) -> str:
        """The serial console as virtlogd logged it (every boot: the last ones up to CONSOLE_TAIL)."""
        with self._errors(f"console of {robot}"):
            vol = self._vol(self._refreshed(self._pool()), self.clone_volumes(robot)["console"])
            if vol is None:
                return ""
            size = vol.info()[1]
            return self._download(vol, max(0, size - CONSOLE_TAIL)).decode(errors="replace")

    # -- snapshots: golden volumes --------------------------------------------------------------
    def build_snapshot(self, repo: str, distro: str, plat, agents: tuple[str, ...], software, digest: str, bare: bool,
                       progress) -> SnapshotRecord:
        """Ability.LOCAL_BUILD: the golden volume made on this machine. The recipe's image is built
        on the local Docker engine as the Docker backend builds its snapshot (the same recipe,
        agents, software and bare variant; no image is downloaded), goldens.build turns it into a qcow2
        with its kernel and initramfs, and those are uploaded to the pool. The intermediate image
        is removed after; the layers under it stay the next build's cache."""
        import tempfile

        from ..docker.images import DEFAULT_BASE, build_snapshot_image
        from ..sdk import docker_module
        from . import goldens

        docker = docker_module()
        try:
            client = docker.from_env(timeout=900)
            client.ping()
        except docker.errors.DockerException as exc:
            raise CcrpError(f"the libvirt backend builds its golden volume with a local Docker engine, and none "
                            f"answers ({type(exc).__name__})", hint="start it: bash scripts/docker-engine.sh") from None
        tag = build_snapshot_image(client, repo, self.fleet, distro, DEFAULT_BASE, plat, agents, software, bare,
                                   owner_labels(self.fleet, "snapshot") | {"ccrp-software": digest}, progress)
        try:
            with tempfile.TemporaryDirectory(prefix="ccrp-golden-") as tmp:
                golden = goldens.build(client, tag, Path(tmp), progress)
                progress(f"uploading the golden volume ({golden.qcow2.stat().st_size >> 20} MB) to pool "
                         f"{self.settings.pool}")
                self._pool(create=True)
                return self.import_golden(golden.qcow2, golden.kernel, golden.initrd, golden.virtual_size)
        finally:
            try:
                client.images.remove(tag, force=True)
            except docker.errors.APIError:  # in use or gone: `ccrp gc` on Docker finds it
                pass
            client.close()

    def import_golden(self, qcow2: Path, kernel: Path, initrd: Path, virtual_size: int, robot: str | None = None) -> SnapshotRecord:
        """Upload a golden disk (goldens.py builds it) with its kernel and initramfs as the fleet's
        volumes; a failure leaves none of the three."""
        name = f"{self.name('golden', *([robot] if robot else []), stamp())}.qcow2"
        stem = name.removesuffix(".qcow2")
        with self._errors(f"import of {name}"):
            pool = self._pool()
            done = []
            try:
                for vol, path, fmt, size in ((name, qcow2, "qcow2", virtual_size), (f"{stem}.vmlinuz", kernel, "raw", None),
                                             (f"{stem}.initrd", initrd, "raw", None)):
                    self._upload(pool, vol, path, fmt, size)
                    done.append(vol)
            except BaseException:
                for vol in done:
                    self._delete_vol(pool, vol)
                raise
            return self._snapshot_record(self._refreshed(pool).storageVolLookupByName(name))

    def _snapshot_record(self, vol) -> SnapshotRecord:
        m = GOLDEN.match(vol.name())
        when = dt.datetime.strptime(m["stamp"], "%Y%m%d%H%M%S").isoformat() if m else ""
        return SnapshotRecord(id=vol.name(), name=vol.name(), created=when, source=(m["robot"] if m else None) or "build",
                              size_mb=round(vol.info()[2] / 1e6, 1))

    def list_snapshots(self) -> list[SnapshotRecord]:
        with self._errors("list snapshots"):
            pool = self._refreshed(self._pool())
            vols = [v for v in pool.listAllVolumes(0) if (m := GOLDEN.match(v.name())) and m["fleet"] == self.fleet]
            return sorted((self._snapshot_record(v) for v in vols), key=lambda s: s.created)

    def delete_snapshot(self, snapshot_id: str) -> None:
        m = GOLDEN.match(snapshot_id)
        if not m or m["fleet"] != self.fleet:
            raise CcrpError(f"{snapshot_id} is not a snapshot of fleet {self.fleet!r}", hint="ccrp snapshot list")
        with self._errors(f"delete snapshot {snapshot_id}"):
            pool = self._refreshed(self._pool())
            if not self._delete_vol(pool, snapshot_id):
                raise CcrpError(f"snapshot {snapshot_id} not found", hint="ccrp snapshot list")
            stem = snapshot_id.removesuffix(".qcow2")
            for extra in (f"{stem}.vmlinuz", f"{stem}.initrd"):
                self._delete_vol(pool, extra)

    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord:
        """The stopped clone's disk flattened into a new golden volume (libvirt copies it through
        its backing chain), with the kernel and initramfs it boots. A running clone is refused:
        QEMU holds its disk's write lock, and the copy (`qemu-img convert`) failed on it even with
        the VM paused (measured)."""
        with self._errors(f"snapshot of {robot}"):
            dom, _info = self._domain(robot)
            if dom is None:
                raise CcrpError(f"robot {robot!r} has no clone", hint=f"ccrp clone create --robot {robot}")
            if dom.isActive():
                raise CcrpError(f"the clone of {robot} is running: a libvirt snapshot copies a stopped clone's disk",
                                hint=f"ccrp clone stop --robot {robot}, then snapshot it")
            pool = self._refreshed(self._pool())
            target = f"{self.name('golden', robot, stamp())}.qcow2"
            stem = target.removesuffix(".qcow2")
            import xml.etree.ElementTree as ET

            os_ = ET.fromstring(dom.XMLDesc(0)).find("os")
            sources = [(pool.storageVolLookupByName(self.clone_volumes(robot)["disk"]), target, "qcow2")]
            sources += [(self.conn.storageVolLookupByPath(os_.findtext(tag)), f"{stem}.{ext}", "raw")
                        for tag, ext in (("kernel", "vmlinuz"), ("initrd", "initrd"))]
            done = []
            try:
                for src, new, fmt in sources:
                    self.api(f"copy volume {new}", pool.createXMLFrom, xmldefs.volume(new, src.info()[1], fmt), src, 0)
                    done.append(new)
            except BaseException:
                for new in done:
                    self._delete_vol(pool, new)
                raise
            return self._snapshot_record(pool.storageVolLookupByName(target))

    # -- everything owned ------------------------------------------------------------------------
    def list_owned(self) -> list[OwnedResource]:
        """Domains (by metadata), then volumes and networks (by name), in deletion order."""
        with self._errors("list owned resources"):
            found = [OwnedResource(kind="instance", id=d.UUIDString(), name=d.name(), robot=i.labels.get(LABEL_ROBOT))
                     for d, i in self._domains()]
            # Power devices first: they hold their robot's power line volume (docker/robots.py).
            found += [OwnedResource(kind="robot_sim", id=c.id[:12], name=c.name, robot=c.labels.get(LABEL_ROBOT))
                      for c in sorted(self._sims(), key=lambda c: c.labels.get(LABEL_ROLE) != "power-sim")]
            pool = self._refreshed(self._pool())
            names = [v.name() for v in pool.listAllVolumes(0) if self._owns_name(v.name())]
            goldens = {n.removesuffix(".qcow2") for n in names if GOLDEN.match(n)}
            for name in names:
                stem, dot, ext = name.rpartition(".")
                if m := GOLDEN.match(name):  # a snapshot; its kernel and initramfs go with it
                    found.append(OwnedResource(kind="image", id=name, name=name, robot=m["robot"]))
                elif not (ext in ("vmlinuz", "initrd") and stem in goldens):
                    m = CLONE_VOLUME.match(name.removeprefix(self.name("cri") + "-"))
                    found.append(OwnedResource(kind="volume", id=name, name=name, robot=m["robot"] if m else None))
            found += [OwnedResource(kind="network", id=n.name(), name=n.name())
                      for n in self.conn.listAllNetworks(0) if n.name() in (self.public_net, self.common_net)]
            found += self._forwards()
            order = ("instance", "robot_sim", "port_forward", "volume", "network", "image")
            return with_roles(sorted(found, key=lambda r: order.index(r.kind)), ROLES)

    def delete_owned(self, resource: OwnedResource) -> None:
        with self._errors(f"delete {resource.kind} {resource.id}"):
            if resource.kind == "instance":
                try:
                    dom = self.conn.lookupByUUIDString(resource.id)
                except self.libvirt.libvirtError as exc:
                    if self._missing(exc, "VIR_ERR_NO_DOMAIN"):
                        raise CcrpError(f"instance {resource.id} is gone") from None
                    raise
                if not self._owns_name(dom.name()) or not self._is_owned(xmldefs.domain_info(dom.XMLDesc(0)).labels):
                    raise CcrpError(f"domain {dom.name()} is not fleet {self.fleet!r}'s; not deleting it")
                if dom.isActive():
                    dom.destroy()
                dom.undefine()
            elif resource.kind == "robot_sim":
                self._delete_sim(resource.id)
            elif resource.kind == "port_forward":
                if resource.robot is None or resource.id != forward.comment(self.fleet, resource.robot):
                    raise CcrpError(f"port forward {resource.id} is not fleet {self.fleet!r}'s; not deleting it")
                if not forward.remove(self.fleet, resource.robot):
                    raise CcrpError(f"port forward {resource.id} is gone")
            elif not self._owns_name(resource.id):
                raise CcrpError(f"{resource.kind} {resource.id} is not fleet {self.fleet!r}'s; not deleting it")
            elif resource.kind == "image":
                self.delete_snapshot(resource.id) if GOLDEN.match(resource.id) else \
                    self._delete_vol(self._refreshed(self._pool()), resource.id)
            elif resource.kind == "volume":
                if not self._delete_vol(self._refreshed(self._pool()), resource.id):
                    raise CcrpError(f"volume {resource.id} is gone")
            elif resource.kind == "network":
                if resource.id not in (self.public_net, self.common_net):
                    raise CcrpError(f"network {resource.id} is not fleet {self.fleet!r}'s; not deleting it")
                self._remove_network(resource.id)
            else:
                raise CcrpError(f"unknown resource kind {resource.kind!r}")

    def _delete_sim(self, container_id: str) -> None:
        """A simulated robot or power device of the fleet; its veth goes with its network namespace."""
        found = [c for c in self._sims() if c.id.startswith(container_id)]
        if not found:
            raise CcrpError(f"simulated robot {container_id} is gone or not fleet {self.fleet!r}'s")
        found[0].remove(force=True, v=True)
        if found[0].labels.get(LABEL_ROLE) == "robot-sim":
            self.release_robot_port(found[0].labels.get(LABEL_ROBOT, ""))

    def _remove_network(self, name: str) -> bool:
        net = self._network(name)
        if net is None:
            return False
        if net.isActive():
            self.api(f"stop network {name}", net.destroy)
        self.api(f"undefine network {name}", net.undefine)
        return True

    def teardown(self) -> list[str]:
        """Every domain, volume and network of the fleet; golden volumes stay (snapshots outlive
        the fleet's clones, as on the clouds)."""
        with self._errors(f"teardown of fleet {self.fleet}"):
            doomed = [r for r in self.list_owned() if r.kind != "image"]
            for r in doomed:
                if r.kind in ("instance", "robot_sim", "port_forward"):
                    self.delete_owned(r)
            pool = self._refreshed(self._pool())
            for r in doomed:
                if r.kind == "volume":
                    self._delete_vol(pool, r.id)
                elif r.kind == "network":
                    self._remove_network(r.id)
            return [_shown(r) for r in doomed]

    def leftovers(self) -> list[str]:
        return [_shown(r) for r in self.list_owned() if r.kind != "image"]

    # -- doctor, quotas ---------------------------------------------------------------------------
    def check_credentials(self) -> str:
        with self._errors(f"libvirt at {self.settings.uri}"):
            v = self.conn.getLibVersion()
            host = self.conn.getHostname()
            probed = self._probed()
            accel = self.settings.accel
            if accel == "auto":
                found = probed.get(self.settings.uri)
                accel = f"auto: {found} ({probed.get(self.settings.uri + ' why', '')})" if found else \
                    "auto (probed at the first clone's boot)"
            return f"libvirt {v // 1_000_000}.{v // 1000 % 1000}.{v % 1000} on {host} ({self.settings.uri}), accel {accel}"

    def quotas(self, robots: Sequence[str] = ()) -> list[Quota]:
        """The libvirt host's room for new clones, each of its own numbers (docs/libvirt.md
        "Quotas"), whoever's the domains and volumes are:

        - memory (MiB): the host's memory against what its running domains were given;
        - vCPUs: the host's CPUs times provider.vcpu_overcommit against its running domains' vCPUs;
        - disk (MiB) of the storage pool: its file system's size against what is used on it plus what
          the clones' overlays in the pool (any fleet's) have not taken yet of provider.overlay_mb;
          one new clone takes overlay_mb. Left out while the pool does not exist (no golden volume
          either: `fleet up` has nothing to boot yet).

        A stopped domain takes no memory or vCPU (starting it again is not held here), its overlay
        keeps its disk. Every clone has the fleet's size: no robot's differs."""
        mib = 1 << 20
        scope = f"libvirt host {self.settings.uri}"
        with self._errors("host resources"):
            _model, memory_mb, cpus, *_ = self.conn.getInfo()
            running = [d.info() for d in self.conn.listAllDomains(self.libvirt.VIR_CONNECT_LIST_DOMAINS_ACTIVE)]
            found = [
                Quota(name="memory (MiB)", scope=scope, limit=float(memory_mb),
                      used=round(sum(i[2] for i in running) / 1024, 1), per_clone=float(self.settings.memory_mb),
                      hint="lower provider.memory_mb, or give the host more memory"),
                Quota(name=f"vCPUs ({cpus} CPUs x vcpu_overcommit {self.settings.vcpu_overcommit:g})", scope=scope,
                      limit=float(cpus) * self.settings.vcpu_overcommit, used=float(sum(i[3] for i in running)),
                      per_clone=float(self.settings.vcpus),
                      hint="lower provider.vcpus, or raise provider.vcpu_overcommit (the clones get slower)"),
            ]
            pool = self._pool_if_active()
            if pool is not None:
                _state, capacity, _allocation, available = pool.info()
                owed = sum(max(0, self.settings.overlay_mb * mib - v.info()[2]) for v in pool.listAllVolumes(0)
                           if OVERLAY.match(v.name()))
                found.append(Quota(
                    name=f"disk (MiB) of storage pool {self.settings.pool}", scope=scope, limit=round(capacity / mib, 1),
                    used=round((capacity - available + owed) / mib, 1), per_clone=float(self.settings.overlay_mb),
                    hint=f"free space where pool {self.settings.pool} is, or lower provider.overlay_mb "
                         f"(each clone's expected writes)"))
            return found

    def _pool_if_active(self):
        """The storage pool, refreshed (its free space and volumes' allocations as they are now), or
        None when it does not exist or is stopped."""
        try:
            pool = self.api("look up the storage pool", self.conn.storagePoolLookupByName, self.settings.pool)
        except self.libvirt.libvirtError as exc:
            if self._missing(exc, "VIR_ERR_NO_STORAGE_POOL"):
                return None
            raise
        return self._refreshed(pool) if pool.isActive() else None

    def close(self) -> None:
        super().close()
        try:
            self.conn.close()
        except self.libvirt.libvirtError:
            pass
