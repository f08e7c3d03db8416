import json
import multiprocessing
import os
import stat
import time

import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.models.state import FleetState, RobotRecord
from ccrp_cli.store import FleetStore, atomic_write


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


def _hold_lock(home, ready, release):
    store = FleetStore("lab", home=home)
    with store.lock():
        ready.set()
        release.wait(10)


def test_lock_excludes_a_second_run(tmp_path):
    ctx = multiprocessing.get_context("fork")
    ready, release = ctx.Event(), ctx.Event()
    holder = ctx.Process(target=_hold_lock, args=(tmp_path, ready, release))
    holder.start()
    try:
        assert ready.wait(10)
        store = FleetStore("lab", home=tmp_path)
        t0 = time.monotonic()
        with pytest.raises(CcrpError, match=rf"locked by another ccrp run \(pid {holder.pid}\)"):
            with store.lock(timeout=0.5):
                pass
        assert time.monotonic() - t0 >= 0.5
    finally:
        release.set()
        holder.join(10)
    with store.lock(timeout=1):  # released when the holder exits
        pass


def test_corrupt_or_future_state_is_a_clear_error(tmp_path):
    store = FleetStore("lab", home=tmp_path)
    atomic_write(store.state_path, "{not json")
    with pytest.raises(CcrpError, match="not valid JSON"):
        store.load_state()
    atomic_write(store.state_path, json.dumps({"schema_version": 99, "fleet": "lab"}))
    with pytest.raises(CcrpError, match="schema_version 99") as info:
        store.load_state()
    assert info.value.hint == "upgrade ccrp"
