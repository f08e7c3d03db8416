"""libvirt provider: a clone is a VM on the libvirt host of `provider.uri` (qemu:///system by
default; a remote host over qemu+ssh:// as libvirt supports it). Its disk is a qcow2 overlay backed
by the fleet's golden volume (copy-on-write: a clone's disk costs only its writes), it boots the
golden volume's kernel and initramfs directly, and cloud-init reads a NoCloud seed (an ISO volume)
with the user-data ccrp renders for the clouds. Its public side is the fleet's NAT network (the
host reaches it; its address is a DHCP lease), its common side an isolated network with the static
address of the addressing plan. Transport is SSH with host keys pinned from the serial console,
which virtlogd writes into the storage pool (read back through libvirt, so remote hosts work too).

This class is the domains' lifecycle; it composes the backend's client (client.py), its networks
(network.py), golden volumes (images.py) and what the fleet owns (owned.py)."""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from ...errors import CcrpError
from ...models.inventory import Inventory
from ..base import LABEL_ROBOT, CloneRecord, CloneSpec, CloneState, Origin, OwnedResource, Quota, RobotAttachment, \
    SnapshotRecord, owner_labels
from ..cloud import CloudProvider
from . import INFO, forward, images, network, owned, seed, xmldefs
from .client import LibvirtClient

# virDomainState (dom.state()[0]) -> libvirt's word, then ccrp's.
WORDS = ("nostate", "running", "blocked", "paused", "shutdown", "shutoff", "crashed", "pmsuspended")
STATES = {"nostate": CloneState.PENDING, "running": CloneState.RUNNING, "blocked": CloneState.RUNNING,
          "paused": CloneState.STOPPED, "shutdown": CloneState.STOPPING, "shutoff": CloneState.STOPPED,
          "crashed": CloneState.ERROR, "pmsuspended": CloneState.STOPPED}
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


def _listening(host: str, port: int = 22) -> bool:
    import socket

    try:
        socket.create_connection((host, port), timeout=2).close()
        return True
    except OSError:
        return False


class LibvirtProvider(CloudProvider):
    kind = "libvirt"
    abilities = INFO.abilities
    images, owned = images, owned  # snapshots and owned resources: CloudProvider hands them the client
    # VMs boot on the libvirt host's CPUs (emulated ones, under TCG): a few at a time.
    max_parallel = 4
    boot_timeout = 900

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        super().__init__(inv, workdir)
        self.client = LibvirtClient(inv, workdir)
        self.settings = self.client.settings
        self._lock = threading.Lock()
        self._accel: str | None = None
        self._emulated: dict[str, bool] = {}  # robot -> its domain runs under TCG

    # -- the fleet's networks (network.py) -------------------------------------------------------
    def bootstrap(self) -> None:
        network.check_settings(self.client)
        # The operator key before clones are made in parallel: each would otherwise make its own when
        # there is none, the last one written wins, and the others' clones refuse it (measured).
        self.operator_public_key()
        network.bootstrap(self.client)

    def public_ip(self, common_ip: str) -> str:
        return network.public_ip(self.client, common_ip)

    # -- simulated robots (Ability.ROBOT_ATTACH, robots.py) ----------------------------------------
    def attach_robot(self, robot: str, index: int) -> RobotAttachment:
        """On no Docker network: its port on the fleet's NAT network is its only interface."""
        port = network.robot_port(self.client, robot, index)
        return RobotAttachment(network="none", name=port.network, address=str(port.address.ip), attach=port.attach)

    def detach_robot(self, robot: str) -> None:
        network.release_robot_port(self.client, robot)

    # -- snapshots: golden volumes (images.py) -----------------------------------------------------
    def build_snapshot(self, repo: str, distro: str, plat, agents: tuple[str, ...], software, digest: str, bare: bool,
                       progress) -> SnapshotRecord:
        return images.build_snapshot(self.client, repo, distro, plat, agents, software, digest, bare, progress)

    def import_golden(self, qcow2: Path, kernel: Path, initrd: Path, virtual_size: int, robot: str | None = None) -> SnapshotRecord:
        return images.import_golden(self.client, qcow2, kernel, initrd, virtual_size, robot)

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
        c = self.client
        try:
            c.conn.getDomainCapabilities(None, "x86_64", None, "kvm", 0)
        except c.libvirt.libvirtError as exc:
            return "tcg", f"libvirt offers no KVM here ({c.message(exc)[:120]})"
        pool = c.pool()
        log_name = c.name("kvm-probe") + xmldefs.CONSOLE_SUFFIX
        log_path = f"{xmldefs.pool_path(pool.XMLDesc(0))}/{log_name}"
        t0, seen, dom = time.monotonic(), "", None
        try:  # virtlogd writes the log even for a guest QEMU could not start: it goes in any case
            try:
                dom = c.conn.createXML(xmldefs.probe_domain(c.name("kvm-probe"), kernel, initrd, log_path), 0)
            except c.libvirt.libvirtError as exc:
                # QEMU's own line says why ("failed to set MSR 0x10a to 0x69" without vmx/svm), after libvirt's words.
                said = c.message(exc).split("qemu-system-x86_64: ")
                why = next((part for part in said if part.startswith("error: ")), said[-1])
                return "tcg", f"a KVM guest did not start ({why.strip()[:160]})"
            while time.monotonic() - t0 < PROBE_TIMEOUT:
                vol = c.vol(c.refreshed(pool), log_name)
                seen = c.download(vol).decode(errors="replace") if vol is not None else ""
                if PROBE_MARK.search(seen):
                    return "kvm", f"a KVM guest started its initramfs in {time.monotonic() - t0:.1f} s"
                if not dom.isActive():
                    break
                time.sleep(0.5)
        finally:
            if dom is not None:
                try:
                    dom.destroy()
                except c.libvirt.libvirtError:
                    pass  # ended by itself (panic=-1, on_reboot destroy)
            c.delete_vol(c.refreshed(pool), log_name)
        return "tcg", f"a KVM guest did not reach its initramfs in {PROBE_TIMEOUT:.0f} s ({seen.strip()[-80:]!r})"

    def _record(self, dom, info: xmldefs.DomainInfo, origin: Origin | None = None) -> CloneRecord:
        c = self.client
        word = WORDS[dom.state(0)[0]] if dom.state(0)[0] < len(WORDS) else "unknown"
        mac = info.macs.get(c.public_net)
        robot = info.labels.get(LABEL_ROBOT, "")
        fw = network.vpn_forward(c, robot, info.common_ip)
        return CloneRecord(robot=robot, provider_id=dom.UUIDString(),
                           state=CloneState.of(word, STATES), status=word,
                           public_ip=network.reserved(c, mac) if mac else None, common_ip=info.common_ip, origin=origin,
                           endpoint=fw.endpoint if fw else None)

    def query(self) -> dict[str, CloneRecord]:
        c = self.client
        with c.errors("list clones"):
            return {r.robot: r for r in (self._record(d, i) for d, i in c.domains(role="clone"))}

    def timeout_scale(self, robot: str) -> int:
        """TCG_SLOWDOWN for a clone emulated by TCG (its domain type is qemu), else 1."""
        c = self.client
        with self._lock:
            known = self._emulated.get(robot)
        if known is None:
            dom, _info = c.domain(robot)
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
        if rec is not None and (ip := rec.public_ip):
            try:
                poll(lambda: (_listening(ip), None), timeout=timeout, interval=2.0)
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
        c = self.client
        dom, _info = c.domain(robot)
        if dom is None or xmldefs.GUEST_AGENT not in dom.XMLDesc(0):
            return None
        deadline = time.monotonic() + timeout
        while True:
            try:
                behind, _rtt = self._clock_behind(dom)
                break
            except c.libvirt.libvirtError:
                # The agent starts with the guest's udev (its port appears) and may not answer yet.
                if time.monotonic() >= deadline:
                    return None
                time.sleep(1.0)
        # The guest applies the time it is sent some milliseconds after the host read it (tens
        # under TCG on a loaded host: 15 and 69 ms behind, measured): each round adds what the
        # clone is still behind by to the next time sent, until that is within the reading's error.
        lead = 0.0
        with c.errors(f"clock of the clone of {robot}"):
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

    def run_instance(self, spec: CloneSpec) -> CloneRecord:
        """Define and start the clone's VM, or start the one that exists; roll back only what this
        attempt created."""
        c = self.client
        INFO.fit_user_data(spec.user_data)
        fw = network.vpn_forward(c, spec.robot, spec.common_ip)
        if fw is not None:  # before the VM: its first boot is when a robot may first dial
            forward.ensure(fw)
        with c.errors(f"clone of {spec.robot}"):
            dom, info = c.domain(spec.robot)
            if dom is not None:
                state = dom.state(0)[0]
                if state == c.libvirt.VIR_DOMAIN_PAUSED:
                    c.api("resume domain", dom.resume)
                elif not dom.isActive():
                    c.api("start domain", dom.create)
                    return self._record(dom, info, Origin.RESUMED)
                return self._record(dom, info, Origin.REUSED)
            created: list[str] = []
            pool = c.pool()
            try:
                dom = self._define(spec, pool, created)
                c.api("start domain", dom.create)
            except BaseException as exc:
                left = self._rollback(pool, spec.robot, created)
                if fw is not None:
                    forward.remove(self.fleet, spec.robot)
                if left and isinstance(exc, CcrpError):
                    exc.message += f" (rollback left {', '.join(left)}: `ccrp gc` removes them)"
                raise
            return self._record(dom, xmldefs.domain_info(dom.XMLDesc(0)), Origin.CREATED)

    def _define(self, spec: CloneSpec, pool, created: list[str]):
        c = self.client
        disk_path, kernel, initrd = images.golden(c, spec.image)
        vols = c.clone_volumes(spec.robot)
        for stale in vols.values():  # left by an attempt that died before defining its domain
            c.delete_vol(c.refreshed(pool), stale)
        self.create_overlay(pool, vols["disk"], spec.image, disk_path)
        created.append(vols["disk"])
        public_mac, common_mac = c.macs(spec.robot)
        network.reserve(c, public_mac, network.public_ip(c, spec.common_ip), spec.hostname)
        iso = seed.seed_iso(spec.user_data, spec.instance_id, spec.hostname,
                            seed.network_config(public_mac, common_mac, spec.common_ip, self.inv.common.cidr))
        c.upload(pool, vols["seed"], iso, "raw")
        created.append(vols["seed"])
        console = f"{xmldefs.pool_path(pool.XMLDesc(0))}/{vols['console']}"
        created.append(vols["console"])  # virtlogd makes it at the first start
        xml = xmldefs.domain(xmldefs.DomainSpec(
            name=c.domain_name(spec.robot), title=f"ccrp clone of robot {spec.robot} (fleet {self.fleet})",
            labels=owner_labels(self.fleet, spec.role, spec.robot), common_ip=spec.common_ip,
            accel=self.accel(kernel, initrd), memory_mb=self.settings.memory_mb, vcpus=self.settings.vcpus,
            pool=self.settings.pool, disk=vols["disk"], seed=vols["seed"], kernel=kernel, initrd=initrd,
            console_log=console,
            nics=(xmldefs.Nic(c.public_net, public_mac), xmldefs.Nic(c.common_net, common_mac))))
        dom = c.api("define domain", c.conn.defineXML, xml)
        created.append(f"domain:{c.domain_name(spec.robot)}")
        return dom

    def create_overlay(self, pool, name: str, image: str, disk_path: str) -> None:
        """A clone's disk: qcow2 volume `name` of golden volume `image`'s virtual size, backed by it
        (at `disk_path`): it holds only the clone's writes (bench/libvirt.py times this)."""
        c = self.client
        capacity = pool.storageVolLookupByName(image).info()[1]
        c.api("create the overlay", pool.createXML, xmldefs.volume(name, capacity, "qcow2", backing=disk_path), 0)

    def footprint(self, robot: str) -> dict[str, float]:
        """What the robot's clone takes of the host now: its overlay's allocation on disk (MB) and
        its QEMU process's resident memory (MiB; absent while the domain is off)."""
        c = self.client
        with c.errors(f"footprint of {robot}"):
            dom, _info = c.domain(robot)
            vol = c.vol(c.refreshed(c.pool()), c.clone_volumes(robot)["disk"])
            found = {"overlay_mb": round(vol.info()[2] / 1e6, 1)} if vol is not None else {}
            if dom is not None and dom.isActive():
                found["rss_mib"] = round(dom.memoryStats().get("rss", 0) / 1024, 1)
            return found

    def _rollback(self, pool, robot: str, created: list[str]) -> list[str]:
        c = self.client
        left = []
        for item in reversed(created):
            try:
                if item.startswith("domain:"):
                    self._remove_domain(robot)
                else:
                    c.delete_vol(c.refreshed(pool), item)
            except Exception:  # noqa: BLE001 - best effort: report, never mask the real failure
                left.append(item)
        return left

    def _remove_domain(self, robot: str) -> bool:
        c = self.client
        dom, _info = c.domain(robot)
        if dom is None:
            return False
        if dom.isActive():
            c.api("destroy domain", dom.destroy)
        c.api("undefine domain", dom.undefine)
        return True

    def stop_instance(self, robot: str) -> bool:
        """The ACPI power button: systemd in the clone shuts it down (autostop's poweroff ends the
        same way). Pressed again every PRESS_AGAIN s while the VM runs, for up to PRESS_FOR s (times
        the TCG slowdown): a press before the guest's kernel has loaded its button driver, early in
        its boot, is lost (the contract suite's clones are stopped right after they start). A guest
        still running then does not listen (a hung kernel): its power is cut, as the clouds' stop
        does after its grace period, so that `clone restart` restarts a clone that no longer answers."""
        c = self.client
        with c.errors(f"stop clone of {robot}"):
            dom, _info = c.domain(robot)
            if dom is None or dom.state(0)[0] != c.libvirt.VIR_DOMAIN_RUNNING:
                return False
            # paramiko still took the old connection for active after the VM's power-off, and the
            # first command after a restart was reset: closed now.
            self.transport.forget(robot)
            deadline = time.monotonic() + PRESS_FOR * self.timeout_scale(robot)
            while dom.isActive():
                try:
                    c.api("shut down domain", dom.shutdown)
                except c.libvirt.libvirtError:
                    if dom.isActive():
                        raise
                    break  # it powered off between the check and the press
                pressed = time.monotonic()
                while dom.isActive() and time.monotonic() - pressed < PRESS_AGAIN:
                    time.sleep(0.5)
                if time.monotonic() > deadline and dom.isActive():
                    # QEMU ends on SIGTERM (its caches flushed to the overlay), the domain stays defined.
                    c.api("power off domain", dom.destroyFlags, c.libvirt.VIR_DOMAIN_DESTROY_GRACEFUL)
                    break
            return True

    def terminate(self, robot: str) -> bool:
        """The robot's VM and its volumes (overlay, seed, console)."""
        c = self.client
        with c.errors(f"delete clone of {robot}"):
            with self._lock:
                self._emulated.pop(robot, None)
            self.transport.forget(robot)
            existed = self._remove_domain(robot)
            network.unreserve(c, c.macs(robot)[0])
            if any(r.robot == robot for r in network.forwards(c)):
                forward.remove(self.fleet, robot)
            pool = c.refreshed(c.pool())
            for name in c.clone_volumes(robot).values():
                c.delete_vol(pool, name)
            return existed

    def console_output(self, robot: str) -> str:
        """The serial console as virtlogd logged it (every boot: the last ones up to CONSOLE_TAIL)."""
        c = self.client
        with c.errors(f"console of {robot}"):
            vol = c.vol(c.refreshed(c.pool()), c.clone_volumes(robot)["console"])
            if vol is None:
                return ""
            size = vol.info()[1]
            return c.download(vol, max(0, size - CONSOLE_TAIL)).decode(errors="replace")

    # -- doctor, quotas ---------------------------------------------------------------------------
    def check_credentials(self) -> str:
        c = self.client
        with c.errors(f"libvirt at {self.settings.uri}"):
            v = c.conn.getLibVersion()
            host = c.conn.getHostname()
            probed = self._probed()
            accel: str = self.settings.accel
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
        c = self.client
        mib = 1 << 20
        scope = f"libvirt host {self.settings.uri}"
        with c.errors("host resources"):
            _model, memory_mb, cpus, *_ = c.conn.getInfo()
            running = [d.info() for d in c.conn.listAllDomains(c.libvirt.VIR_CONNECT_LIST_DOMAINS_ACTIVE)]
            found = [
                Quota(name="memory (MiB)", scope=scope, limit=float(memory_mb),
                      used=round(sum(i[2] for i in running) / 1024, 1), per_clone=float(self.settings.memory_mb),
                      hint="lower provider.memory_mb, or give the host more memory"),
                Quota(name=f"vCPUs ({cpus} CPUs x vcpu_overcommit {self.settings.vcpu_overcommit:g})", scope=scope,
                      limit=float(cpus) * self.settings.vcpu_overcommit, used=float(sum(i[3] for i in running)),
                      per_clone=float(self.settings.vcpus),
                      hint="lower provider.vcpus, or raise provider.vcpu_overcommit (the clones get slower)"),
            ]
            pool = c.pool_if_active()
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

    def close(self) -> None:
        super().close()
        self.client.close()
