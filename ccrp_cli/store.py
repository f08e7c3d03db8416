"""Per-fleet on-disk store: $CCRP_HOME/<fleet>/ with state.json, pki/ and bundles.

Writes are atomic (temp file in the same directory, fsync, os.replace, fsync of the directory),
files are 0600 and directories 0700, and a lock file keeps two ccrp runs from writing at once.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from pydantic import ValidationError

from .errors import CcrpError
from .models.state import SCHEMA_VERSION, FleetState

FILE_MODE = 0o600
DIR_MODE = 0o700


def ccrp_home() -> Path:
    return Path(os.environ.get("CCRP_HOME") or ".ccrp")


def ensure_dir(path: Path) -> Path:
    """Create `path` and any missing parents as 0700 (existing directories are left alone)."""
    if not path.is_dir():
        ensure_dir(path.parent)
        with contextlib.suppress(FileExistsError):
            path.mkdir(mode=DIR_MODE)
            os.chmod(path, DIR_MODE)  # mkdir's mode is masked by the umask
    return path


def atomic_write(path: Path, data: bytes | str, mode: int = FILE_MODE, durable: bool = True) -> None:
    """Replace `path` with `data` so that a crash leaves either the old or the new file.

    durable=False skips the fsyncs, for outputs that can be rendered again (bundles)."""
    if isinstance(data, str):
        data = data.encode()
    ensure_dir(path.parent)
    # A unique temp name: threads of one run (fleet up fan-out) may write the same file.
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    if not durable:
        return
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


class FleetStore:
    def __init__(self, fleet: str, home: Path | None = None) -> None:
        self.fleet = fleet
        self.root = (home or ccrp_home()) / fleet

    @property
    def pki_dir(self) -> Path:
        return self.root / "pki"

    @property
    def state_path(self) -> Path:
        return self.root / "state.json"

    @contextlib.contextmanager
    def lock(self, timeout: float = 30.0) -> Iterator[None]:
        """Exclusive lock on the fleet; waits up to `timeout` seconds for another run."""
        ensure_dir(self.root)
        fd = os.open(self.root / ".lock", os.O_RDWR | os.O_CREAT, FILE_MODE)
        deadline = time.monotonic() + timeout
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                        raise
                    if time.monotonic() >= deadline:
                        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
                        raise CcrpError(
                            f"fleet {self.fleet!r} is locked by another ccrp run (pid {holder})",
                            hint="wait for it to finish; the lock is released when that process exits",
                        ) from None
                    time.sleep(0.1)
            os.ftruncate(fd, 0)
            os.pwrite(fd, str(os.getpid()).encode(), 0)
            yield
        finally:
            os.close(fd)  # closing the descriptor releases the flock

    def load_state(self) -> FleetState:
        try:
            raw = self.state_path.read_text()
        except FileNotFoundError:
            return FleetState(fleet=self.fleet)
        try:
            data = json.loads(raw)
        except json.JSONDecodeError as exc:
            raise CcrpError(
                f"{self.state_path} is not valid JSON ({exc.msg} at line {exc.lineno})",
                hint="restore it from a backup or move it away; `ccrp gc` finds resources it forgot",
            ) from None
        version = data.get("schema_version") if isinstance(data, dict) else None
        if isinstance(version, int) and version > SCHEMA_VERSION:
            raise CcrpError(
                f"{self.state_path} has schema_version {version}; this ccrp understands {SCHEMA_VERSION}",
                hint="upgrade ccrp",
            )
        try:
            return FleetState.model_validate(data)
        except ValidationError as exc:
            raise CcrpError(f"{self.state_path} does not match the state schema: {exc.errors()[0]['msg']}") from None

    def save_state(self, state: FleetState) -> None:
        atomic_write(self.state_path, state.model_dump_json(indent=2) + "\n")
