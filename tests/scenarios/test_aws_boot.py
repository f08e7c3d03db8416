"""The user's path on AWS, through `ccrp` run as a separate process exactly as typed, against moto
whose EC2 instances really boot (tests/fakes/aws_boot.py, scenarios/backend_aws.py):

vpn init; snapshot bake (no image named: ccrp resolves Debian 12 from the public SSM parameter, a
builder instance boots it and installs the recipe with cloud-init from Debian's mirror and PyPI,
then CreateImage captures it); clone create for nao1 (the clone boots from that AMI, gets its
Elastic IP, SSH pinned from the console output, secrets pushed); status --json shows it running
with its master reachable; clone exec; fleet down; gc --dry-run finds nothing; moto holds nothing
tagged with the fleet; no instance container is left, and the backend's exit removes every
container, network and image of the run.

The bake installs packages from the internet: about two minutes here. Timings are printed
(pytest -s shows them).
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
pytest.importorskip("boto3")
pytest.importorskip("moto.server")
pytest.importorskip("paramiko")

from tests.scenarios.backend_aws import open_backend  # noqa: E402

FLEET = "awsboot"


def _image_buildable() -> bool:
    if shutil.which("mmdebstrap"):
        return True
    try:
        with docker.from_env(timeout=30) as client:
            client.images.get(DEBIAN_12)
        return True
    except docker.errors.DockerException:
        return False


def test_user_path_on_a_booting_ec2(tmp_path):
    if not _image_buildable():
        pytest.skip(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it")
    timings: dict[str, float] = {}
    t_start = time.monotonic()

    with open_backend(tmp_path, FLEET) as backend:
        fake = backend.fake
        inv = str(backend.inventory)
        assert "profile" not in backend.inventory.read_text() and "image" not in backend.inventory.read_text()

        def ccrp(step: str, *args: str, timeout: float = 900):
            t0 = time.monotonic()
            proc = backend.ccrp(*args, timeout=timeout)
            timings[step] = round(time.monotonic() - t0, 1)
            assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
            assert proc.returncode == 0, (f"ccrp {' '.join(args)} exited {proc.returncode}\n"
                                          f"stderr: {proc.stderr[-3000:]}\nstdout: {proc.stdout[-2000:]}\n"
                                          f"fake errors: {fake.errors}")
            return proc

        try:
            ccrp("vpn init", "vpn", "init", "-i", inv)
            ccrp("snapshot bake", "snapshot", "bake", "-i", inv, timeout=1800)
            snaps = json.loads(ccrp("snapshot list", "snapshot", "list", "-i", inv, "--json").stdout)
            assert len(snaps) == 1 and snaps[0]["id"] in fake.captured, (snaps, fake.captured)
            # The builder booted the Debian 12 AMI the SSM parameter names, and is gone.
            assert fake.calls["ssm GetParameter"] >= 1

            ccrp("clone create nao1", "clone", "create", "-i", inv, "--robot", "nao1")
            rows = {r["robot"]: r for r in json.loads(ccrp("status", "status", "-i", inv, "--json").stdout)}
            nao1 = rows["nao1"]
            assert nao1["status"] == "running" and nao1["phase"] == "ready", nao1
            assert nao1["master_reachable"] is True and nao1["secrets"] is True, nao1
            assert ipaddress.IPv4Address(nao1["public_ip"]) in ipaddress.IPv4Network(fake.internet_cidr), nao1
            assert rows["nao2"]["status"] == "absent", rows["nao2"]
            out = ccrp("clone exec", "clone", "exec", "-i", inv, "--robot", "nao1", "--", "hostname").stdout
            assert out.strip() == "cri-nao1", out
            running = [c for c in fake.boot.leftovers() if c.startswith("container ")]
            assert len(running) == 1, running  # the clone; the builder was terminated

            ccrp("fleet down", "fleet", "down", "-i", inv)
            leaked = json.loads(ccrp("gc --dry-run", "gc", "-i", inv, "--dry-run", "--json").stdout)
            assert leaked == [], leaked
            assert backend.owned() == [], backend.owned()
            fake.wait_idle()
            assert [c for c in fake.boot.leftovers() if c.startswith("container ")] == []
            assert fake.errors == {}, fake.errors
        finally:
            print(f"\nAWS user path timings (s): {timings}; EC2 calls: {sum(fake.calls.values())}")
        boot = fake.boot
    assert boot.leftovers() == [], boot.leftovers()
    print(f"total {time.monotonic() - t_start:.1f} s (fake's start and cleanup included)")
