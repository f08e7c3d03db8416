"""The user's path on GCP, through `ccrp` as typed, against the GCE fake whose instances really boot
(scenarios/backend_gcp.py): vpn init, snapshot bake (a builder booted from Debian 12 installs the
recipe with cloud-init from Debian's mirror and PyPI, then is captured), fleet up (clones boot from
that image, SSH pinned from the serial console, secrets pushed), status --json, clone exec, fleet
down and gc --dry-run; nothing of the fleet is left in the fake, and the backend's exit removes
every container, network and image of the run.

The bake installs packages from the internet: minutes. Timings are printed (pytest -s shows them).
"""

from __future__ import annotations

import ipaddress
import json
import shutil
import time

import pytest

from tests.fakes.cloudboot import DEBIAN_12, docker_available

_NO_DOCKER = docker_available()

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(_NO_DOCKER is not None, reason=f"needs a running Docker engine ({_NO_DOCKER})"),
]

docker = pytest.importorskip("docker")
pytest.importorskip("google.cloud.compute_v1")
pytest.importorskip("paramiko")

from tests.scenarios.backend_gcp import open_backend

FLEET = "gboot"


def _image_buildable() -> bool:
    if shutil.which("mmdebstrap"):
        return True
    try:
        with docker.from_env(timeout=30) as client:
            client.images.get(DEBIAN_12)
        return True
    except docker.errors.DockerException:
        return False


def test_user_path_on_a_booting_gce(tmp_path):
    if not _image_buildable():
        pytest.skip(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it")
    timings: dict[str, float] = {}

    with open_backend(tmp_path, FLEET, echo=True) as backend:
        inv = str(backend.inventory)

        def ccrp(step: str, *args: str, timeout: float = 900):
            t0 = time.monotonic()
            proc = backend.ccrp(*args, timeout=timeout)
            timings[step] = round(time.monotonic() - t0, 1)
            if proc.returncode != 0:
                for name, console in backend.fake.last_console.items():  # e.g. the builder's, for the why
                    print(f"--- console of deleted instance {name} (last 80 lines)")
                    print("\n".join(console.splitlines()[-80:]))
            assert proc.returncode == 0, f"ccrp {' '.join(args)} exited {proc.returncode}:\n{proc.stderr[-3000:]}"
            return proc

        ccrp("vpn init", "vpn", "init", "-i", inv)

        bake = ccrp("snapshot bake", "snapshot", "bake", "-i", inv, "--json", timeout=2400)
        (snapshot,) = json.loads(bake.stdout)  # JSON on stdout, progress on stderr
        assert "booting the builder" in bake.stderr and "builder terminated" in bake.stderr
        fake = backend.fake
        assert snapshot["name"] in fake.images and snapshot["name"] in fake.docker_images
        assert not any(i.labels.get("ccrp-role") == "builder" for i in fake.instances.values())

        up = ccrp("fleet up", "fleet", "up", "-i", inv, "--json", timeout=1200)
        results = {r["robot"]: r for r in json.loads(up.stdout)}
        assert results["nao1"]["action"] == "created", results

        status = ccrp("status", "status", "-i", inv, "--json")
        rows = {r["robot"]: r for r in json.loads(status.stdout)}
        nao1 = rows["nao1"]
        assert nao1["status"] == "RUNNING" and nao1["master_reachable"] is True, nao1
        assert ipaddress.ip_address(nao1["public_ip"]) in ipaddress.ip_network(fake.internet_cidr)
        assert nao1["secrets"] is True, nao1

        exec_ = ccrp("clone exec", "clone", "exec", "-i", inv, "--robot", "nao1", "--",
                     "sh", "-c", "hostname; cloud-init status; systemctl is-active ccrp-openvpn")
        assert "status: done" in exec_.stdout and exec_.stdout.strip().endswith("active"), exec_.stdout

        ccrp("fleet down", "fleet", "down", "-i", inv)
        gc = ccrp("gc --dry-run", "gc", "-i", inv, "--dry-run", "--json")
        assert json.loads(gc.stdout) == []
        assert backend.owned() == []
        assert not any(fake.boot.has(str(i.id)) for i in fake.instances.values())
        t0 = time.monotonic()
    timings["cleanup"] = round(time.monotonic() - t0, 1)
    print("timings (s):", json.dumps(timings))
