"""The contract harness on this machine's libvirtd (qemu:///system), where it answers
(tests/libvirt_host.py). Clones are real VMs booted from the fleet's golden volume, but a tiny one,
so the suite tests the provider, not cloud-init (as the Docker harness's `sleep` image does): the
Debian cloud kernel and its initramfs with, as the root file system, a static busybox whose init
loads the ACPI button driver and runs acpid, which powers the VM off at the power button (what
`clone stop` presses; a clone's systemd does the same). Built once per machine from Debian's
packages (the image ccrp-test/vm-tiny, tests/tiny_vm.py, shared with the real OpenStack's harness),
a few MB of disk per run.

Faults and delays are injected around each libvirt call the provider makes through its retry layer
(`provider.client.api`), before the call reaches libvirtd: a dropped RPC connection (what the provider
retries) stands for a cloud's throttling. The clones' public ingress is what their firewall lets in
from outside the VPN and the common network, read from the NoCloud seed each VM booted with:
libvirt has no security groups, and the fleet's NAT network lets nothing in from outside the host
but the VPN ports `provider.vpn_forward` forwards (tests/unit/test_libvirt_forward.py)."""

from __future__ import annotations

import ipaddress
import shlex
import subprocess
import threading
import time
import uuid
from collections import Counter
from contextlib import contextmanager

import pytest
import yaml

from ccrp_cli.providers.base import LABEL_FLEET, LABEL_MANAGED, LABEL_ROBOT, LABEL_ROLE

from ..tiny_vm import DISK_BYTES, tiny_files
from .harness import FLEET
from .specs import FAST, OPERATOR_CIDR, Knobs, clone_spec, inventory

PUBLIC_RANGE = "192.168.208.0/20"


def _injected(libvirt, message: str, code: int):
    """A libvirtError carrying `code`, as libvirt-python raises them (its error is read from the C
    library at construction, so this one answers from its own fields)."""

    class Injected(libvirt.libvirtError):
        def get_error_code(self):
            return code

        def get_error_message(self):
            return message

    return Injected(message)


class LibvirtHarness(Knobs):
    kind = "libvirt"

    def __init__(self, provider, conn) -> None:
        self.provider, self.raw, self.libvirt = provider, conn, provider.client.libvirt
        self.calls: Counter = Counter()
        self._lock = threading.Lock()
        self._fraction, self._delay, self._n = 0.0, 0.0, 0
        self._fail_robots: set[str] = set()
        self.foreign: list[str] = []
        self.golden = ""
        api = provider.client.api
        provider.client.api = lambda what, fn, *a, **kw: api(what, self._attempt(what, fn), *a, **kw)

    def _attempt(self, what: str, fn):
        def attempt(*args, **kwargs):
            with self._lock:
                self.calls[what] += 1
                self._n += 1
                throttled = int(self._n * self._fraction) > int((self._n - 1) * self._fraction)
            if self._delay:
                time.sleep(self._delay)
            if throttled:
                raise _injected(self.libvirt, "injected: the RPC connection dropped", self.libvirt.VIR_ERR_RPC)
            robot = fn.__self__.name().removeprefix(f"ccrp-{FLEET}-cri-") if what == "start domain" else None
            if robot in self._fail_robots:  # the domain is defined: the start fails
                self._fail_robots.discard(robot)
                raise _injected(self.libvirt, "injected: cannot start the domain", self.libvirt.VIR_ERR_INTERNAL_ERROR)
            return fn(*args, **kwargs)
        return attempt

    def spec(self, robot: str, index: int):
        return clone_spec(self.provider.inv, robot, index, self.golden)

    # Read straight from libvirtd with a connection of the harness's own, around the provider.
    def _domains(self, robot: str | None = None) -> list:
        from ccrp_cli.providers.libvirt import xmldefs

        found = []
        for dom in self.raw.listAllDomains(0):
            if not dom.name().startswith(f"ccrp-{FLEET}-"):  # others' (the VM test's) may go meanwhile
                continue
            labels = xmldefs.domain_info(dom.XMLDesc(0)).labels
            if labels.get(LABEL_FLEET) == FLEET and labels.get(LABEL_MANAGED) == "true" and (
                    robot is None or labels.get(LABEL_ROBOT) == robot):
                found.append((dom, labels))
        return found

    def _pool(self):
        pool = self.raw.storagePoolLookupByName(self.provider.settings.pool)
        pool.refresh(0)
        return pool

    def _volumes(self, robot: str | None = None) -> list[str]:
        """The fleet's volumes (golden volumes aside: snapshots outlive teardown, as the clouds' images)."""
        prefix = f"ccrp-{FLEET}-" + (f"cri-{robot}" if robot else "")
        return [v.name() for v in self._pool().listAllVolumes(0)
                if v.name().startswith(prefix) and not v.name().startswith(f"ccrp-{FLEET}-golden-")
                and (robot is None or v.name()[len(prefix)] in ".-")]

    def instance_roles(self, robot: str) -> list[str]:
        return [labels.get(LABEL_ROLE, "") for _dom, labels in self._domains(robot)]

    def instances_for(self, robot: str) -> int:
        return sum(labels.get(LABEL_ROLE) == "clone" for _dom, labels in self._domains(robot))

    def owned_ids(self, robot: str | None = None) -> set[str]:
        ids = {dom.UUIDString() for dom, _labels in self._domains(robot)} | set(self._volumes(robot))
        if robot is None:
            ids |= {n.name() for n in self.raw.listAllNetworks(0) if n.name().startswith(f"ccrp-{FLEET}-")}
        return ids

    def add_foreign(self) -> str:
        """A defined domain named like a clone, labelled with another fleet."""
        from ccrp_cli.providers.libvirt import xmldefs

        name = f"ccrp-{FLEET}foreign-cri-robot1"
        xml = (f"<domain type='qemu'><name>{name}</name><uuid>{uuid.uuid4()}</uuid><metadata>"
               f"<ccrp:owner xmlns:ccrp='{xmldefs.NS}'><ccrp:label name='{LABEL_MANAGED}'>true</ccrp:label>"
               f"<ccrp:label name='{LABEL_FLEET}'>other</ccrp:label><ccrp:label name='{LABEL_ROLE}'>clone</ccrp:label>"
               f"<ccrp:label name='{LABEL_ROBOT}'>robot1</ccrp:label></ccrp:owner></metadata>"
               "<memory unit='MiB'>64</memory><os><type arch='x86_64'>hvm</type></os></domain>")
        dom = self.raw.defineXML(xml)
        self.foreign.append(dom.UUIDString())
        return dom.UUIDString()

    def add_leak(self) -> str:
        """The seed of a clone that is gone (say, a crash between writing it and defining the VM)."""
        from ccrp_cli.providers.libvirt import xmldefs

        name = f"ccrp-{FLEET}-cri-ghost-seed.iso"
        self._pool().createXML(xmldefs.volume(name, 1 << 20, "raw"), 0)
        return name

    def exists(self, resource_id: str) -> bool:
        lookups = (self.raw.lookupByUUIDString, self._pool().storageVolLookupByName, self.raw.networkLookupByName)
        for lookup in lookups:
            try:
                lookup(resource_id)
                return True
            except self.libvirt.libvirtError:
                continue
        return False

    def user_data_sent(self, robot: str) -> bytes:
        """The user-data file of the NoCloud seed the robot's VM boots with."""
        seed = self._pool().storageVolLookupByName(f"ccrp-{FLEET}-cri-{robot}-seed.iso")
        return subprocess.run(["isoinfo", "-R", "-i", seed.path(), "-x", "/user-data"], capture_output=True,
                              check=True).stdout

    def public_ingress(self) -> set[tuple[str, int, str]]:
        """What each clone's IPv4 firewall accepts but through the VPN, from loopback or from the
        common network (the fleet's networks are IPv4 only)."""
        common = self.provider.inv.common.cidr
        rules = set()
        for _dom, labels in self._domains():
            data = yaml.safe_load(self.user_data_sent(labels[LABEL_ROBOT]))
            [fw] = [f["content"] for f in data["write_files"] if f["path"].endswith("/firewall.rules")]
            for line in fw.splitlines():
                t = shlex.split(line)
                if t[:2] != ["-A", "INPUT"] or t[-2:] != ["-j", "ACCEPT"] or "--dport" not in t or "-i" in t:
                    continue
                source = t[t.index("-s") + 1] if "-s" in t else "0.0.0.0/0"
                if ipaddress.ip_network(source, strict=False).subnet_of(common):
                    continue
                rules.add((t[t.index("-p") + 1], int(t[t.index("--dport") + 1]), source))
        return rules


@contextmanager
def make_harness(tmp_path):
    from tests.libvirt_host import URI, gate

    if reason := gate():
        pytest.skip(reason)
    import docker
    import libvirt

    from ccrp_cli.ops.init import free, used_networks
    from ccrp_cli.providers.libvirt.provider import LibvirtProvider

    from tests.scenarios.backend import free_cidr

    client = docker.from_env()
    from tests.e2e.fleet import ensure_base

    ensure_base(client)
    files = tiny_files(client)
    used = used_networks()
    # accel tcg: the contract is the provider's, not the host's; no probe VM per test.
    inv = inventory({"kind": "libvirt", "accel": "tcg", "memory_mb": 512, "vcpus": 1,
                     "public_cidr": free_cidr(PUBLIC_RANGE), "operator_cidr": OPERATOR_CIDR},
                    common={"cidr": free("common", used)}, vpn={"pool": free("vpn", used)})
    raw = libvirt.open(URI)
    provider = LibvirtProvider(inv, tmp_path / "store")
    provider.client.backoff = FAST
    harness = None
    # What a killed run left of fleet "ct" on this host: a stopped domain of robot1 made `create`
    # resume it (CI: test_create_is_idempotent saw RESUMED).
    provider.teardown()
    try:
        provider.bootstrap()
        harness = LibvirtHarness(provider, raw)
        harness.golden = provider.import_golden(files["qcow2"], files["kernel"], files["initrd"], DISK_BYTES).id
        yield harness
    finally:
        try:
            if harness:
                harness.throttle(0)
                harness.delay(0)
                for dom_id in harness.foreign:
                    raw.lookupByUUIDString(dom_id).undefine()
            provider.teardown()
            for snap in provider.list_snapshots():
                provider.delete_snapshot(snap.id)
        finally:
            provider.close()
            raw.close()
            client.close()
