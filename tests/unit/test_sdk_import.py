"""docker-py without its ssh:// transport (providers/sdk.py): cheaper, and paramiko stays importable."""

from __future__ import annotations

import json
import os
import subprocess
import sys

PROBE = """
import json, sys, threading
from ccrp_cli.providers.sdk import docker_module
errors = []
def ssh_side():  # ccrp's SSH transport importing paramiko while docker-py is imported
    try:
        import paramiko  # noqa: F401
    except Exception as exc:
        errors.append(repr(exc))
t = threading.Thread(target=ssh_side)
t.start()
docker = docker_module()
t.join()
from docker.transport import UnixHTTPAdapter  # noqa: F401
print(json.dumps({"ssh_adapter": hasattr(sys.modules["docker.transport"], "SSHHTTPAdapter"), "errors": errors,
                  "client": type(docker.DockerClient).__name__}))
"""


def probe(**env: str) -> dict:
    environ = {k: v for k, v in os.environ.items() if k != "DOCKER_HOST"} | env
    out = subprocess.run([sys.executable, "-c", PROBE], env=environ, capture_output=True, text=True, check=True).stdout
    return json.loads(out)


def test_docker_sdk_comes_without_its_ssh_adapter_and_paramiko_stays_importable():
    assert probe() == {"ssh_adapter": False, "errors": [], "client": "type"}


def test_docker_host_over_ssh_keeps_the_adapter():
    assert probe(DOCKER_HOST="ssh://ops@engine.example")["ssh_adapter"] is True
