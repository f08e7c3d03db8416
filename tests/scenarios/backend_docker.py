"""The local Docker backend for scenarios: the real engine; clones are ccrp's own containers."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path

from .backend import Backend, free_cidr, inventory_text


@contextmanager
def open_backend(tmp_path: Path, fleet: str):
    import docker

    client = docker.from_env(timeout=300)
    label = {"label": [f"ccrp-fleet={fleet}"]}

    def owned() -> list[str]:
        return ([f"container {c.name}" for c in client.containers.list(ignore_removed=True, all=True, filters=label)]
                + [f"volume {v.name}" for v in client.volumes.list(filters=label)]
                + [f"network {n.name}" for n in client.networks.list(filters=label)])

    public = free_cidr("172.22.0.0/15")
    common = free_cidr("10.200.0.0/14")
    inv = tmp_path / "inventory.yaml"
    inv.write_text(inventory_text(fleet, f"  kind: docker\n  public_cidr: {public}\n", common, "10.84.0.0/16"))
    try:
        yield Backend(kind="docker", inventory=inv, home=tmp_path / "home", owned=owned)
    finally:
        for c in client.containers.list(ignore_removed=True, all=True, filters=label):
            c.remove(force=True, v=True)
        for v in client.volumes.list(filters=label):
            v.remove(force=True)
        for n in client.networks.list(filters=label):
            n.remove()
        for image in client.images.list(filters=label):  # the run's snapshots
            client.images.remove(image.id, force=True)
        client.close()
