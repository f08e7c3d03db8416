"""What the three clouds (openstack, gcp, aws) share: the operator SSH key, host-key pinning
from the console output, secrets pushed over SSH, and calls wrapped by retry.call.

A cloud provider subclasses CloudProvider and implements the primitives marked `cloud:`;
push_files / exec / wait_ready then work the same way on every cloud.
"""

from __future__ import annotations

from pathlib import Path

from ..models.inventory import Inventory
from ..retry import Backoff, ErrorClass, call
from .base import CloneRecord, CloneSpec, OwnedResource, SnapshotRecord

# Login user of the snapshot images (Ubuntu cloud images); cloud-init creates it.
SSH_USER = "ubuntu"


class CloudProvider:
    kind = "cloud"
    backoff = Backoff()

    def __init__(self, inv: Inventory, workdir: Path) -> None:
        # workdir = the fleet's store root (.ccrp/<fleet>): operator SSH key, pinned host keys.
        self.inv, self.fleet, self.workdir = inv, inv.fleet, Path(workdir)

    # -- operator SSH key (ed25519, 0600 in the fleet store; only the public half leaves) ----------
    @property
    def ssh_key_path(self) -> Path:
        return self.workdir / "ssh" / "id_ed25519"

    def operator_public_key(self) -> str:
        """The fleet's operator key, created on first use: "ssh-ed25519 AAAA... ccrp-<fleet>"."""
        from cryptography.hazmat.primitives import serialization
        from cryptography.hazmat.primitives.asymmetric import ed25519

        from ..store import atomic_write, ensure_dir

        key_path = self.ssh_key_path
        if not key_path.exists():
            ensure_dir(key_path.parent)
            key = ed25519.Ed25519PrivateKey.generate()
            atomic_write(key_path, key.private_bytes(
                serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()))
        key = serialization.load_ssh_private_key(key_path.read_bytes(), password=None)
        pub = key.public_key().public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH)
        return f"{pub.decode()} ccrp-{self.fleet}"

    # -- retries (one place) -----------------------------------------------------------------
    def classify_error(self, exc: BaseException) -> ErrorClass:  # cloud: per SDK
        raise NotImplementedError

    def api(self, what: str, fn, *args, **kwargs):
        """Every SDK call goes through here: retried on throttling / 5xx, classified otherwise."""
        return call(fn, *args, classify=self.classify_error, what=what, backoff=self.backoff, **kwargs)

    # -- cloud primitives ------------------------------------------------------------------
    def bootstrap(self) -> None: ...  # cloud: network, security groups, key pair, routes (create or reuse)
    def run_instance(self, spec: CloneSpec) -> CloneRecord: ...  # cloud: idempotent, rolls back own partials
    def query(self) -> dict[str, CloneRecord]: ...  # cloud: instances with the fleet's labels
    def terminate(self, robot: str) -> bool: ...  # cloud: owned only; with its public IP / volumes
    def console_output(self, robot: str) -> str: ...  # cloud: serial console text
    def create_snapshot(self, robot: str, name: str) -> SnapshotRecord: ...
    def list_snapshots(self) -> list[SnapshotRecord]: ...
    def delete_snapshot(self, snapshot_id: str) -> None: ...
    def teardown(self) -> list[str]: ...
    def list_owned(self) -> list[OwnedResource]: ...
    def delete_owned(self, resource: OwnedResource) -> None: ...

    # -- shared: SSH transport (transport/ssh.py) ------------------------------------------------
    def wait_ready(self, robot: str, timeout: float = 600) -> None: ...
    def push_files(self, robot: str, files: list, restart: list[str] = ()) -> None: ...
    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]: ...
