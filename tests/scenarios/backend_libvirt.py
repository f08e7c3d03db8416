"""The libvirt backend for scenarios: this machine's libvirtd (qemu:///system), clones as real VMs
booted from qcow2 overlays of the golden volume `ccrp snapshot build` makes; simulated robots are
containers of this host on the fleet's NAT bridge (the provider attaches them, so no sim network).

Opt-in (tests/libvirt_host.py): each VM boot takes minutes of QEMU (TCG on this machine).

`owned()` lists, by the names ccrp gives them, the fleet's domains, networks and volumes in
libvirt, and the containers labelled with the fleet (its simulated robots); golden volumes are
the fleet's snapshots, which outlive `fleet down` like the clouds' images, and are removed when
the scenario ends.

Faults: "quota" lowers provider.vcpu_overcommit in the inventory, as an operator would, so the
host's vCPUs are all taken by the fleet's two clones: `fleet scale` must refuse before it creates
anything. libvirt has no zones and no API throttling to inject.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

import pytest

from tests.libvirt_host import URI, gate

from .backend import Backend, free_cidr, hello_software, inventory_text

def unavailable() -> str | None:
    """Why the scenario cannot run here (None: it can)."""
    return gate(scenario=True)
PROVIDER = "  kind: libvirt\n  memory_mb: 1536\n  vcpus: 2\n  public_cidr: {public}\n"


def _owned(fleet: str) -> list[str]:
    import docker
    import libvirt

    prefix = f"ccrp-{fleet}-"
    conn = libvirt.open(URI)
    client = docker.from_env(timeout=120)
    try:
        found = [f"domain {d.name()}" for d in conn.listAllDomains(0) if d.name().startswith(prefix)]
        found += [f"network {n.name()}" for n in conn.listAllNetworks(0) if n.name().startswith(prefix)]
        for pool in conn.listAllStoragePools(0):
            if pool.isActive():
                pool.refresh(0)
                found += [f"volume {v.name()}" for v in pool.listAllVolumes(0) if v.name().startswith(prefix)
                          and not v.name().startswith(f"{prefix}golden-")]
        found += [f"container {c.name}" for c in
                  client.containers.list(all=True, ignore_removed=True, filters={"label": f"ccrp-fleet={fleet}"})]
        return sorted(found)
    finally:
        client.close()
        conn.close()


def _remove(fleet: str) -> None:
    """Everything of the fleet, golden volumes and the recipe's images included."""
    import docker
    import libvirt

    prefix = f"ccrp-{fleet}-"
    conn = libvirt.open(URI)
    client = docker.from_env(timeout=300)
    try:
        for dom in conn.listAllDomains(0):
            if dom.name().startswith(prefix):
                if dom.isActive():
                    dom.destroy()
                dom.undefine()
        for c in client.containers.list(all=True, ignore_removed=True, filters={"label": f"ccrp-fleet={fleet}"}):
            c.remove(force=True, v=True)
        for net in conn.listAllNetworks(0):
            if net.name().startswith(prefix):
                if net.isActive():
                    net.destroy()
                net.undefine()
        for pool in conn.listAllStoragePools(0):
            if pool.isActive():
                pool.refresh(0)
                for vol in pool.listAllVolumes(0):
                    if vol.name().startswith(prefix):
                        vol.delete(0)
        for image in client.images.list(filters={"label": f"ccrp-fleet={fleet}"}):
            client.images.remove(image.id, force=True)
    finally:
        client.close()
        conn.close()


@contextmanager
def open_backend(tmp_path: Path, fleet: str):
    inv = tmp_path / "inventory.yaml"
    provider = PROVIDER.format(public=free_cidr("192.168.144.0/20"))
    # The fleet's own software (a catkin workspace; docs/workloads.md): in the golden volume `snapshot
    # build` makes, then deployed to the VMs over SSH by the deploy step.
    inv.write_text(inventory_text(fleet, provider, free_cidr("10.220.0.0/16"), "10.86.0.0/16") + hello_software(tmp_path))

    @contextmanager
    def quota():  # the host's vCPUs (its CPUs x vcpu_overcommit) no more than the fleet's two clones take
        import libvirt

        conn = libvirt.open(URI)
        try:
            cpus = conn.getInfo()[2]
        finally:
            conn.close()
        if cpus > 4:  # vcpu_overcommit is 1 at least
            pytest.skip(f"this libvirt host has {cpus} CPUs: two 2-vCPU clones cannot fill them")
        original = inv.read_text()
        kind = PROVIDER.split("\n")[0] + "\n"
        inv.write_text(original.replace(kind, f"{kind}  vcpu_overcommit: {4 / cpus:g}\n", 1))
        try:
            yield
        finally:
            inv.write_text(original)

    try:
        yield Backend(kind="libvirt", inventory=inv, home=tmp_path / "home", owned=lambda: _owned(fleet),
                      faults={"quota": quota}, nodes=["hello", "launched"])
    finally:
        _remove(fleet)
