"""A fleet from nothing, as a new user starts one: `ccrp init` in an empty directory, then
`ccrp fleet up` with no `-i` (the directory's ccrp.yaml), which makes the fleet's PKI and builds
its snapshot because it has neither yet. Swept away at the end, even on failure."""

from __future__ import annotations

import json
import os
import secrets
import string
import subprocess
import sys
import warnings

import pytest
import yaml

from tests.e2e.fleet import NO_DOCKER, sweep

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(NO_DOCKER is not None, reason=f"needs a running Docker engine ({NO_DOCKER})"),
]


def test_init_then_fleet_up_starts_a_fleet_from_nothing(tmp_path, clone_images):
    import docker

    clone_images("noetic")  # the snapshot fleet up builds comes from Docker's cache

    name = "e2n" + "".join(secrets.choice(string.ascii_lowercase + string.digits) for _ in range(6))
    work = tmp_path / "lab"
    work.mkdir()
    env = {**os.environ, "CCRP_HOME": str(tmp_path / "home")}
    env.pop("CCRP_INVENTORY", None)

    def ccrp(*args: str) -> subprocess.CompletedProcess:
        proc = subprocess.run([sys.executable, "-m", "ccrp_cli", *args], cwd=work, env=env, capture_output=True,
                              text=True, timeout=900)
        assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
        assert proc.returncode == 0, f"ccrp {' '.join(args)} exited {proc.returncode}: {proc.stderr[-3000:]}"
        return proc

    client = docker.from_env(timeout=300)
    try:
        ccrp("init", "--provider", "docker", "--robots", "nao1", "--fleet", name)
        assert yaml.safe_load((work / "ccrp.yaml").read_text())["fleet"] == name
        up = ccrp("fleet", "up", "--json")
        assert "using inventory ccrp.yaml" in up.stderr
        assert f"fleet {name!r} had no PKI yet" in up.stderr and f"fleet {name!r} has no snapshot yet" in up.stderr
        assert [r["action"] for r in json.loads(up.stdout)] == ["created"]
        (row,) = json.loads(ccrp("status", "--json").stdout)
        assert row["robot"] == "nao1" and row["master_reachable"] is True
        again = ccrp("fleet", "up", "--json")  # now it has both: nothing made, nothing built
        assert "had no PKI" not in again.stderr and "no snapshot" not in again.stderr
        assert [r["action"] for r in json.loads(again.stdout)] == ["reused"]
    finally:
        subprocess.run([sys.executable, "-m", "ccrp_cli", "fleet", "down"], cwd=work, env=env, capture_output=True,
                       timeout=600)
        left = sweep(client, name)
        if left:
            warnings.warn(f"fleet {name}: could not remove {left}", stacklevel=1)
