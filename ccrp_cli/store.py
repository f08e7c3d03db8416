"""Per-fleet on-disk store: $CCRP_HOME/<fleet>/ with state.json, pki/ and bundles.

Writes are atomic (temp file in the same directory, fsync, os.replace, fsync of the directory),
files are 0600 and directories 0700, and a lock file keeps two ccrp runs from writing at once.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import functools
import json
import os
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from pydantic import ValidationError

from .errors import CcrpError, InputError
from .models.state import SCHEMA_VERSION, FleetState

FILE_MODE = 0o600
DIR_MODE = 0o700
LOCK_WAIT_ENV = "CCRP_LOCK_WAIT"
DEFAULT_LOCK_WAIT = 600.0
# A random id made once per state directory: what the Docker backend's snapshot images are
# labelled with, so `ccrp gc` can tell an image of a directory deleted and made again (a new id)
# from one whose state still lives (providers/docker/snapshot_images.py).
STATE_ID_FILE = "state-id"


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


def read_state_id(root: Path) -> str | None:
    """The id in the state directory `root`; None when it has none (or `root` is gone). Other
    errors (a directory this user may not read) pass: the caller cannot judge, so must keep."""
    try:
        return (root / STATE_ID_FILE).read_text().strip() or None
    except (FileNotFoundError, NotADirectoryError):
        return None


def ensure_state_id(root: Path) -> str:
    """The id of the state directory `root`, made (with `root`) if missing. Two runs making it at
    once agree: the file appears whole (a hard link of a written temp file, which fails when it
    exists) and whoever lost reads the winner's."""
    found = read_state_id(root)
    if found:
        return found
    import secrets

    path = root / STATE_ID_FILE
    tmp = _write_temp(path, secrets.token_hex(16) + "\n", FILE_MODE)
    try:
        os.link(tmp, path)
        _fsync_dir(root)
    except FileExistsError:
        pass
    finally:
        tmp.unlink(missing_ok=True)
    found = read_state_id(root)
    if not found:  # there, but empty: written by hand
        raise CcrpError(f"{path} is empty", hint="remove it: ccrp makes a new state id")
    return found


def atomic_write(path: Path, data: bytes | str, mode: int = FILE_MODE, durable: bool = True) -> None:
    """Replace `path` with `data` so that a crash leaves either the old or the new file.

    durable=False skips the fsyncs, for outputs that can be rendered again (bundles)."""
    tmp = _write_temp(path, data, mode, durable)
    _replace(tmp, path)
    if durable:
        _fsync_dir(path.parent)


def atomic_write_all(files: list[tuple[Path, bytes | str, int]]) -> None:
    """atomic_write of each (path, data, mode), durable, in no order among them: a crash leaves
    each file old or new. Their fsyncs run side by side, which the filesystem commits together
    (a robot's seven PKI files: 7.5 ms one after the other, 4.6 ms side by side, measured).
    A batch of many files (`fleet up` issuing a whole fleet) is made durable by one syncfs of
    its filesystem before the renames and one after, in place of an fsync per file and per
    directory (1,000 robots: about 8,000 fsyncs)."""
    batch = len(files) >= SYNCFS_BATCH and _syncfs_available()
    pool = _fsync_pool()
    temps = list(pool.map(lambda f: _try(_write_temp, *f, not batch), files))
    failed = [t for t in temps if isinstance(t, BaseException)]
    if failed:
        for tmp in temps:
            if isinstance(tmp, Path):
                tmp.unlink(missing_ok=True)
        raise failed[0]
    if batch:
        _syncfs_all({path.parent for path, _, _ in files})
    for i, (tmp, (path, _, _)) in enumerate(zip(temps, files)):
        try:
            os.replace(tmp, path)
        except BaseException:
            for left in temps[i:]:
                left.unlink(missing_ok=True)
            raise
    if batch:
        _syncfs_all({path.parent for path, _, _ in files})
    else:
        list(pool.map(_fsync_dir, {path.parent for path, _, _ in files}))


SYNCFS_BATCH = 256


@functools.cache
def _libc():
    import ctypes

    return ctypes.CDLL(None, use_errno=True)


def _syncfs_available() -> bool:
    try:
        return hasattr(_libc(), "syncfs")
    except OSError:
        return False


def _syncfs_all(directories: set[Path]) -> None:
    """syncfs(2) once per filesystem holding one of `directories`."""
    seen: set[int] = set()
    for directory in directories:
        fd = os.open(directory, os.O_RDONLY)
        try:
            dev = os.fstat(fd).st_dev
            if dev not in seen:
                seen.add(dev)
                if _libc().syncfs(fd) != 0:
                    import ctypes

                    err = ctypes.get_errno()
                    raise OSError(err, os.strerror(err), str(directory))
        finally:
            os.close(fd)


def _try(fn: Callable, *args):
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001 - handed back to the caller, who raises it
        return exc


@functools.cache
def _fsync_pool() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=8, thread_name_prefix="ccrp-fsync")


def _write_temp(path: Path, data: bytes | str, mode: int, durable: bool = True) -> Path:
    """`data` in a new temp file beside `path`, fsynced when durable."""
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
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp


def _replace(tmp: Path, path: Path) -> None:
    try:
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def _fsync_dir(directory: Path) -> None:
    dir_fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def file_identity(st: os.stat_result) -> tuple[int, int, int]:
    """What tells one version of a file from another: atomic_write gives every version a new
    inode, so a file read once can be kept in memory until this changes."""
    return (st.st_ino, st.st_mtime_ns, st.st_size)


def lock_wait() -> float:
    """Seconds a run waits for another run's fleet lock: $CCRP_LOCK_WAIT, else 10 minutes (a
    `fleet up` of many clones takes minutes)."""
    raw = os.environ.get(LOCK_WAIT_ENV, "").strip()
    if not raw:
        return DEFAULT_LOCK_WAIT
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not value >= 0:  # NaN too
        raise InputError(f"{LOCK_WAIT_ENV}={raw!r} is not a number of seconds", hint=f"e.g. {LOCK_WAIT_ENV}=1800")
    return value


def _read_holder(fd: int) -> tuple[int | None, str]:
    """(pid, command) from the lock file's first line; (None, "") while it names nobody."""
    first = os.pread(fd, 256, 0).decode(errors="replace").split("\n", 1)[0]
    pid, _, command = first.strip().partition(" ")
    return (int(pid), command.strip()) if pid.isdigit() else (None, "")


def _alive(pid: int | None) -> bool:
    if pid is None:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _describe(pid: int | None, command: str) -> str:
    return f"ccrp run pid {pid if pid is not None else '?'}" + (f" ({command})" if command else "")


class FleetStore:
    def __init__(self, fleet: str, home: Path | None = None, command: str = "",
                 on_wait: Callable[[str], None] = lambda message: None) -> None:
        self.fleet = fleet
        self.root = (home or ccrp_home()) / fleet
        # What this run is (`fleet up`), written into the lock file for a second run to show,
        # and where that second run says it waits: the CLI sets both (cli/options.py open_fleet).
        self.command = command
        self.on_wait = on_wait
        # state.json as last read or written: a run that handles robots one at a time (issuing
        # each one's certificates) parses it once, not once per robot.
        self._state: tuple[tuple, FleetState] | None = None

    @property
    def pki_dir(self) -> Path:
        return self.root / "pki"

    @property
    def state_path(self) -> Path:
        return self.root / "state.json"

    @contextlib.contextmanager
    def lock(self, timeout: float | None = None) -> Iterator[None]:
        """Exclusive lock on the fleet for this run's mutating command.

        The lock is a flock on `.lock`: the kernel frees it when the holder exits, however it
        ends (kill -9 included), and the descriptor is not inherited by child processes. The
        file names the holder (`<pid> <command>`). A second run says once, through `on_wait`, whom
        it waits for, then waits up to `timeout` seconds (default: $CCRP_LOCK_WAIT, else 10 min)
        before failing in one line."""
        if timeout is None:
            timeout = lock_wait()
        ensure_dir(self.root)
        fd = os.open(self.root / ".lock", os.O_RDWR | os.O_CREAT, FILE_MODE)
        started = time.monotonic()
        told = False
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except OSError as exc:
                    if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                        raise
                waited = time.monotonic() - started
                pid, command = _read_holder(fd)
                if waited >= timeout:
                    raise CcrpError(
                        f"fleet {self.fleet!r} is still locked by {_describe(pid, command)} after waiting "
                        f"{timeout:g} s",
                        hint=f"let that run finish (or stop it: the lock goes with its process), then run this "
                             f"again; {LOCK_WAIT_ENV}=SECONDS waits longer",
                    ) from None
                # The holder writes its name just after it takes the lock: until a live pid shows
                # (or a second has passed), the file may still name the previous holder.
                if not told and (_alive(pid) or waited >= 1.0):
                    self.on_wait(f"waiting for {_describe(pid, command)} to finish with fleet {self.fleet!r}...")
                    told = True
                time.sleep(0.1)
            # Written before truncating: a reader sees the first line whole at every moment.
            holder = f"{os.getpid()} {self.command}".strip() + "\n"
            os.pwrite(fd, holder.encode(), 0)
            os.ftruncate(fd, len(holder.encode()))
            self._remove_stale_temp_files()
            yield
        finally:
            os.close(fd)  # closing the descriptor releases the flock

    def _remove_stale_temp_files(self) -> None:
        """A run killed while saving state leaves its atomic_write temp file, which no one would
        ever remove. Only runs holding the lock write state.json, so under the lock any such file
        is a dead run's."""
        for stale in self.root.glob(f".{self.state_path.name}.*.tmp"):
            with contextlib.suppress(FileNotFoundError):
                stale.unlink()

    def load_state(self) -> FleetState:
        """The fleet state. Read again only when the file changed, so the object is shared with
        this store's earlier callers: whoever changes it saves it (save_state)."""
        try:
            with open(self.state_path, "rb") as fh:
                identity = file_identity(os.fstat(fh.fileno()))
                if self._state is not None and self._state[0] == identity:
                    return self._state[1]
                raw = fh.read().decode()
        except FileNotFoundError:
            return FleetState(fleet=self.fleet)
        self._state = (identity, self._parse_state(raw))
        return self._state[1]

    def _parse_state(self, raw: str) -> FleetState:
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
        self._state = (file_identity(os.stat(self.state_path)), state)  # under the lock: no one else writes
