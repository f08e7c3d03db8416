"""One VM clone on libvirt, end to end: `ccrp snapshot build` making the golden volume from the
recipe (its Docker image, then providers/libvirt/goldens.py), `ccrp fleet up` creating the clone as a qcow2 overlay booted with a
NoCloud seed of the user-data ccrp renders, `ccrp status` saying it serves, and `ccrp fleet down`
leaving no domain, volume or network of the fleet.

Gated: CCRP_E2E_LIBVIRT=1, a libvirtd answering on qemu:///system (scripts/libvirt.sh) and the
binding installed. CCRP_LIBVIRT_ACCEL (auto, kvm, tcg; default auto) is the inventory's accel."""

from __future__ import annotations

import ipaddress
import json
import os
import secrets
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.slow, pytest.mark.root]


def _gate() -> str | None:
    if os.environ.get("CCRP_E2E_LIBVIRT") != "1":
        return "set CCRP_E2E_LIBVIRT=1 to boot VM clones (needs libvirtd: scripts/libvirt.sh)"
    try:
        import libvirt
    except ImportError:
        return "the libvirt binding is not installed (pip extra libvirt: scripts/libvirt.sh)"
    libvirt.registerErrorHandler(lambda _c, _e: None, None)
    try:
        libvirt.open("qemu:///system").close()
    except libvirt.libvirtError as exc:
        return f"libvirtd does not answer on qemu:///system: {exc}"
    return None


SKIP = _gate()
if SKIP:
    pytest.skip(SKIP, allow_module_level=True)


def ccrp(home: Path, *args: str, timeout: float = 1800) -> subprocess.CompletedProcess:
    env = {**os.environ, "CCRP_HOME": str(home)}
    env.pop("CCRP_INVENTORY", None)
    return subprocess.run([sys.executable, "-m", "ccrp_cli", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)


def free_public(used: list[ipaddress.IPv4Network]) -> str:
    for net in ipaddress.IPv4Network("192.168.144.0/20").subnets(new_prefix=24):
        if not any(net.overlaps(u) for u in used):
            return str(net)
    raise RuntimeError("no free /24 in 192.168.144.0/20 for the fleet's NAT network")


@pytest.fixture(scope="module")
def vm_fleet(tmp_path_factory):
    """A one-robot libvirt fleet whose snapshot is a golden volume `ccrp snapshot build` made;
    everything of it, golden volumes included, is removed at the end whatever happened."""
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops.init import free, used_networks
    from ccrp_cli.providers import get_provider

    tmp = tmp_path_factory.mktemp("libvirt")
    home = tmp / "home"
    os.environ["CCRP_HOME"] = str(home)  # Fleet.open below and the CLI share the state
    used = used_networks()
    inv = {"fleet": f"lv{secrets.token_hex(3)}",
           "provider": {"kind": "libvirt", "accel": os.environ.get("CCRP_LIBVIRT_ACCEL", "auto"), "memory_mb": 1536,
                        "vcpus": 2, "public_cidr": free_public(used)},
           "ros": {"distro": "noetic"}, "vpn": {"pool": free("vpn", used)}, "common": {"cidr": free("common", used)},
           "robots": [{"name": "nao1"}]}
    path = tmp / "ccrp.yaml"
    path.write_text(yaml.safe_dump(inv, sort_keys=False))
    fleet = Fleet.open(path)
    provider = get_provider(fleet.inventory)
    timings: dict[str, float] = {}
    try:
        t0 = time.monotonic()
        built = ccrp(home, "snapshot", "build", "-i", str(path), "--json")
        timings["snapshot build (recipe image + golden volume)"] = time.monotonic() - t0
        assert built.returncode == 0, built.stderr[-3000:]
        state = json.loads((fleet.store.root / "state.json").read_text())
        [record] = [s for s in provider.list_snapshots() if s.id == state["snapshot"]["image"]]
        yield {"home": home, "path": path, "fleet": fleet, "provider": provider, "timings": timings, "golden": record}
    finally:
        try:
            provider.teardown()
            for snap in provider.list_snapshots():
                provider.delete_snapshot(snap.id)
        finally:
            provider.close()
            print(f"\nlibvirt e2e timings (s): {json.dumps({k: round(v, 1) for k, v in timings.items()})}")


def test_vm_clone_serves_and_fleet_down_leaves_nothing(vm_fleet):
    home, path, provider = vm_fleet["home"], str(vm_fleet["path"]), vm_fleet["provider"]
    t0 = time.monotonic()
    up = ccrp(home, "fleet", "up", "-i", path)
    vm_fleet["timings"]["fleet up (1 VM clone)"] = time.monotonic() - t0
    assert up.returncode == 0, up.stderr[-3000:] + "\n--- console ---\n" + provider.console_output("nao1")[-3000:]

    [rec] = provider.query().values()
    assert rec.robot == "nao1" and rec.state.value == "running" and rec.public_ip
    assert ipaddress.IPv4Address(rec.public_ip) in provider.settings.public_cidr
    # The clone's disk is an overlay of the golden volume: only its writes are its own.
    pool = provider._pool()
    disk = pool.storageVolLookupByName(provider.clone_volumes("nao1")["disk"])
    golden = pool.storageVolLookupByName(vm_fleet["golden"].id)
    assert golden.path() in disk.XMLDesc(0)
    vm_fleet["timings"]["overlay MB after fleet up"] = disk.info()[2] / 1e6

    status = ccrp(home, "status", "-i", path, "--json", timeout=300)
    assert status.returncode == 0, status.stderr[-2000:]
    rows = {r["robot"]: r for r in json.loads(status.stdout)}
    row = rows["nao1"]
    assert row["phase"] == "ready" and row["state"] == "running" and row["master_reachable"] is True, row
    assert row["public_ip"] == rec.public_ip and row["secrets"] is True, row

    down = ccrp(home, "fleet", "down", "-i", path, timeout=600)
    assert down.returncode == 0, down.stderr[-2000:]
    assert provider.leftovers() == []
    fleet = vm_fleet["fleet"].name
    conn = provider.conn
    assert not [d.name() for d in conn.listAllDomains(0) if d.name().startswith(f"ccrp-{fleet}-")]
    assert not [n.name() for n in conn.listAllNetworks(0) if n.name().startswith(f"ccrp-{fleet}-")]
    pool.refresh(0)
    assert [v.name() for v in pool.listAllVolumes(0) if v.name().startswith(f"ccrp-{fleet}-")
            and not v.name().startswith(f"ccrp-{fleet}-golden-")] == []
