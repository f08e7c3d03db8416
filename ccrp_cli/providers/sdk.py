"""Importing a backend's SDK at the cost of what ccrp uses of it."""

from __future__ import annotations

import os
import sys
from types import ModuleType


def docker_module() -> ModuleType:
    """docker-py, without its ssh:// transport unless DOCKER_HOST asks for it. docker-py's transport
    package imports its SSH adapter whenever paramiko is installed (every cloud extra installs it),
    and paramiko imports invoke: about half of `import docker`, paid by every `ccrp` call on the
    Docker backend (docs/benchmarks.md). docker-py skips that adapter on ImportError, so only that
    module of docker-py is hidden, for the life of the process: paramiko itself stays importable,
    at any moment, by ccrp's SSH transport in another thread (hiding paramiko even for a moment
    made such a thread fail: "import of paramiko halted")."""
    if "docker" not in sys.modules and not os.environ.get("DOCKER_HOST", "").startswith("ssh://"):
        sys.modules.setdefault("docker.transport.sshconn", None)  # type: ignore[arg-type]
    import docker

    return docker
