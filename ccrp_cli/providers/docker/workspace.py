"""`ccrp deploy`'s workspace build (ops/deploy.py): the fleet's software built once, on this host's
Docker engine whatever the fleet's backend, in the clone image (the snapshot's Dockerfile with the
current software: Docker's layer cache runs only the software's layers), and its install space read
out of the image as a tar. Every clone runs the same Debian 12 platform, so the tar serves every
backend. The core reaches it as providers.build_workspace."""

from __future__ import annotations

from ...errors import CcrpError
from ...models.layout import WORKSPACE
from ...models.inventory import Inventory
from ..base import owner_labels
from . import INFO, images
from .settings import DockerSettings


def local_engine():
    """This machine's Docker engine (DOCKER_HOST), with a one-line error when none answers."""
    from ..sdk import docker_module

    try:
        client = docker_module().from_env(timeout=600)
        client.ping()
        return client
    except Exception as exc:  # noqa: BLE001 - no engine, no socket, no permission: all the same to the user
        raise CcrpError(f"ccrp deploy builds the workspace in the clone image with a local Docker engine, and none "
                        f"answers ({type(exc).__name__})",
                        hint="start Docker on this machine (or set DOCKER_HOST), then run ccrp deploy again") from None


def deploy_repo(fleet: str) -> str:
    return f"ccrp/{fleet}-deploy"


def build_workspace(inv: Inventory, software, agents: tuple[str, ...], progress=lambda msg: None) -> bytes:
    """The tar of the install space (top directory `workspace/`) built from `software`
    (workloads.SnapshotSoftware, with a workspace) in the fleet's clone image, with the `agents` its
    snapshot holds: the same Dockerfile up to the software's layers, so those alone run."""
    from ...recipes import platform

    client = local_engine()
    try:
        # The Docker backend's platform on every backend: the same Debian 12 and ROS as the cloud
        # recipes install (docs/clouds.md); a Docker fleet's own base image, if it names one.
        plat = platform(inv.ros.distro, INFO.platform)
        base = inv.provider.base_image if isinstance(inv.provider, DockerSettings) else images.DEFAULT_BASE
        images.ensure_base(client, base, plat, progress)
        tag = f"{deploy_repo(inv.fleet)}:{software.digest}"
        progress(f"building workspace {software.digest} in the clone image ({tag}); only the software's layers run")
        labels = owner_labels(inv.fleet, "deploy") | {"ccrp-software": software.digest}
        images.build_clone_image(client, tag, images.dockerfile(inv.fleet, inv.ros.distro, base, plat, software, agents=agents),
                                 labels, progress, images.build_context(plat, progress, inv.ros.distro, software, agents=agents),
                                 what="deploy build")
        # Read out of a container made from the image and never started.
        container = client.containers.create(tag, labels=owner_labels(inv.fleet, "deploy"))
        try:
            stream, _ = container.get_archive(WORKSPACE)
            data = b"".join(stream)
        finally:
            container.remove(force=True)
        _drop_older_builds(client, inv.fleet, tag)
        return data
    finally:
        client.close()


def _drop_older_builds(client, fleet: str, keep: str) -> None:
    """One deploy image per fleet: the last (its layers are the next build's cache)."""
    for image in client.images.list(filters={"label": [f"ccrp-fleet={fleet}", "ccrp-role=deploy"]}):
        if keep not in image.tags:
            try:
                client.images.remove(image.id, force=False)
            except Exception:  # noqa: BLE001, S110 - in use or gone: gc finds it later
                pass
