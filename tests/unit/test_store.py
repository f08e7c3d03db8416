import contextlib
import json
import os
import signal
import stat
import subprocess
import sys
import time

import pytest

from ccrp_cli.errors import CcrpError, InputError
from ccrp_cli.models.state import FleetState, RobotRecord
from ccrp_cli import store as store_mod
from ccrp_cli.store import FleetStore, atomic_write, atomic_write_all, lock_wait
from tests.conftest import LAB, ROOT


def mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def test_state_round_trip_with_modes(tmp_path):
    store = FleetStore("lab", home=tmp_path / "home")
    assert store.load_state() == FleetState(fleet="lab")
    state = FleetState(fleet="lab", robots={"nao1": RobotRecord(index=1, phase="ready")})
    with store.lock():
        store.save_state(state)
    assert store.load_state() == state
    assert json.loads(store.state_path.read_text())["schema_version"] == 1
    assert mode(store.state_path) == 0o600
    assert mode(store.root) == 0o700 and mode(tmp_path / "home") == 0o700
    assert [p.name for p in store.root.iterdir() if p.name.endswith(".tmp")] == []


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path, monkeypatch):
    target = tmp_path / "f.json"
    atomic_write(target, "old")

    def boom(*_a, **_k):
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(OSError):
        atomic_write(target, "new")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.json"]


@pytest.mark.parametrize("count", [3, store_mod.SYNCFS_BATCH])
def test_atomic_write_all_small_batches_fsync_each_file_large_ones_sync_the_filesystem(tmp_path, monkeypatch, count):
    """A fleet's worth of files is made durable by one syncfs before the renames and one after
    (an fsync per file and directory cost 2-4 s at 1,000 robots); a few files by their fsyncs."""
    fsynced, synced = [], []
    real_fsync, real_syncfs = os.fsync, store_mod._syncfs_all
    monkeypatch.setattr(os, "fsync", lambda fd: (fsynced.append(fd), real_fsync(fd)))
    monkeypatch.setattr(store_mod, "_syncfs_all", lambda dirs: (synced.append(set(dirs)), real_syncfs(dirs)))
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "f0").write_text("old")
    files = [(tmp_path / ("a" if i % 2 else "b") / f"f{i}", f"data {i}", 0o600 if i % 3 else 0o644) for i in range(count)]
    atomic_write_all(files)
    for path, data, want in files:
        assert path.read_text() == data and mode(path) == want
    assert [p for p in tmp_path.rglob("*.tmp")] == []
    if count >= store_mod.SYNCFS_BATCH:
        assert synced == [{tmp_path / "a", tmp_path / "b"}] * 2 and fsynced == []
    else:
        assert synced == [] and len(fsynced) == count + 2  # each file, then both directories


def test_atomic_write_all_leaves_every_old_file_when_one_cannot_be_written(tmp_path):
    (tmp_path / "keep").write_text("old")
    (tmp_path / "blocked").mkdir()  # a file cannot be written where a directory is
    files = [(tmp_path / "keep", "new", 0o600), (tmp_path / "blocked" / "x" / "y", "z", 0o600)]
    files += [(tmp_path / f"n{i}", "n", 0o600) for i in range(store_mod.SYNCFS_BATCH)]
    (tmp_path / "blocked" / "x").write_text("a file, not a directory")
    with pytest.raises(OSError):
        atomic_write_all(files)
    assert (tmp_path / "keep").read_text() == "old"
    assert not list(tmp_path.glob("n*")) and not list(tmp_path.rglob("*.tmp"))


# A real process holding the fleet lock as `ccrp fleet up` would: argv = home, seconds to hold,
# and "child" to start a long-lived child process while holding it.
HOLDER = r"""
import pathlib, subprocess, sys, time
from ccrp_cli.store import FleetStore
with FleetStore("lab", home=pathlib.Path(sys.argv[1]), command="fleet up").lock(timeout=0):
    # close_fds=False: the child inherits every descriptor that is inheritable.
    child = subprocess.Popen(["sleep", "60"], close_fds=False) if "child" in sys.argv else None
    print("locked", child.pid if child else "", flush=True)
    time.sleep(float(sys.argv[2]))
"""


@contextlib.contextmanager
def holder(home, seconds: float, *extra: str):
    """A subprocess holding fleet 'lab''s lock for `seconds`; yields (process, its child's pid or None)."""
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(home), str(seconds), *extra],
                            cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        words = proc.stdout.readline().split()
        assert words and words[0] == "locked", f"the holder did not take the lock: {words}"
        yield proc, int(words[1]) if len(words) > 1 else None
    finally:
        proc.kill()
        proc.wait(10)


def ccrp_cli(home, *args, env=()):
    return subprocess.run([sys.executable, "-m", "ccrp_cli", *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=60, env={**os.environ, "CCRP_HOME": str(home), **dict(env)})


def test_second_run_says_whom_it_waits_for_then_proceeds(tmp_path):
    store = FleetStore("lab", home=tmp_path, command="vpn revoke", on_wait=(said := []).append)
    with holder(tmp_path, 1.5) as (proc, _):
        t0 = time.monotonic()
        with store.lock(timeout=30):
            waited = time.monotonic() - t0
            assert (store.root / ".lock").read_text() == f"{os.getpid()} vpn revoke\n"
        assert proc.wait(10) == 0  # the holder ended on its own, after its 1.5 s
    assert said == [f"waiting for ccrp run pid {proc.pid} (fleet up) to finish with fleet 'lab'..."]
    assert 0.5 < waited < 10, waited


def test_cli_waits_for_a_running_command_with_one_message(tmp_path):
    """The holder lets go only once the waiting run has said so (a fixed hold raced the CLI's start
    on a loaded machine: it began after the lock was free and had nothing to wait for)."""
    with holder(tmp_path, 60) as (proc, _):
        run = subprocess.Popen([sys.executable, "-m", "ccrp_cli", "vpn", "init", "-i", str(LAB)], cwd=ROOT,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               env={**os.environ, "CCRP_HOME": str(tmp_path)})
        first = run.stderr.readline()
    out, rest = run.communicate(timeout=60)  # the holder was killed on leaving: the lock is free
    assert run.returncode == 0, first + rest
    lines = (first + rest).splitlines()
    assert lines[0] == f"ccrp: waiting for ccrp run pid {proc.pid} (fleet up) to finish with fleet 'lab'...", lines
    assert sum("waiting" in line for line in lines) == 1 and "CA created" in lines[1], lines


def test_cli_gives_up_after_ccrp_lock_wait_in_one_line(tmp_path):
    with holder(tmp_path, 30) as (proc, _):
        t0 = time.monotonic()
        run = ccrp_cli(tmp_path, "vpn", "init", "-i", str(LAB), env={"CCRP_LOCK_WAIT": "1"})
        took = time.monotonic() - t0
    assert run.returncode == 1, run.stderr
    waiting, error = run.stderr.splitlines()  # exactly two lines: no traceback
    assert waiting.startswith(f"ccrp: waiting for ccrp run pid {proc.pid} (fleet up)"), waiting
    assert error.startswith(f"ccrp: error: fleet 'lab' is still locked by ccrp run pid {proc.pid} (fleet up) "
                            "after waiting 1 s (hint: "), error
    assert "CCRP_LOCK_WAIT=SECONDS" in error
    assert 1 <= took < 15, took
    assert not (tmp_path / "lab" / "pki").exists()  # the waiting run changed nothing


def test_lock_of_a_killed_run_is_free_at_once(tmp_path):
    """flock belongs to the open file: the kernel drops it when the holder dies, even by SIGKILL,
    and a child process the holder started does not inherit it (the descriptor is CLOEXEC)."""
    with holder(tmp_path, 60, "child") as (proc, child):
        try:
            os.kill(proc.pid, signal.SIGKILL)
            assert proc.wait(10) == -signal.SIGKILL
            os.kill(child, 0)  # the holder's child outlives it...
            said = []
            with FleetStore("lab", home=tmp_path, on_wait=said.append).lock(timeout=0):  # ...without the lock
                pass
            assert said == []
        finally:
            os.kill(child, signal.SIGKILL)


# Saves state and stops in the middle of atomic_write (after the temp file is written, before it
# replaces state.json), as a run SIGKILLed at that moment does.
STUCK_WRITER = r"""
import os, pathlib, sys, time
from ccrp_cli.models.state import FleetState
from ccrp_cli.store import FleetStore
store = FleetStore("lab", home=pathlib.Path(sys.argv[1]))
def stuck(fd):
    print("writing", flush=True)
    time.sleep(60)
os.fsync = stuck
with store.lock(timeout=0):
    store.save_state(FleetState(fleet="lab"))
"""


def test_state_temp_file_of_a_killed_run_is_removed_by_the_next_lock(tmp_path):
    store = FleetStore("lab", home=tmp_path)
    with store.lock():
        store.save_state(FleetState(fleet="lab", robots={"nao1": RobotRecord(index=1)}))
    proc = subprocess.Popen([sys.executable, "-c", STUCK_WRITER, str(tmp_path)], cwd=ROOT, stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        proc.kill()
    left = [p.name for p in store.root.iterdir() if p.name.endswith(".tmp")]
    assert len(left) == 1 and left[0].startswith(".state.json."), left
    assert list(store.load_state().robots) == ["nao1"]  # the old state, whole
    other = store.root / ".other.json.x.tmp"  # not state's: left alone
    other.write_text("")
    with store.lock(timeout=0):
        pass
    assert sorted(p.name for p in store.root.iterdir() if p.name.endswith(".tmp")) == [other.name]


def test_lock_wait_comes_from_the_environment(monkeypatch):
    monkeypatch.delenv("CCRP_LOCK_WAIT", raising=False)
    assert lock_wait() == 600
    monkeypatch.setenv("CCRP_LOCK_WAIT", "2.5")
    assert lock_wait() == 2.5
    for bad in ("soon", "-1", "nan"):
        monkeypatch.setenv("CCRP_LOCK_WAIT", bad)
        with pytest.raises(InputError, match="CCRP_LOCK_WAIT"):
            lock_wait()


def test_corrupt_or_future_state_is_a_clear_error(tmp_path):
    store = FleetStore("lab", home=tmp_path)
    atomic_write(store.state_path, "{not json")
    with pytest.raises(CcrpError, match="not valid JSON"):
        store.load_state()
    atomic_write(store.state_path, json.dumps({"schema_version": 99, "fleet": "lab"}))
    with pytest.raises(CcrpError, match="schema_version 99") as info:
        store.load_state()
    assert info.value.hint == "upgrade ccrp"
