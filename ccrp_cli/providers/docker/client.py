"""The Docker engine on this host, for a fleet: the client (every request retried on 429/503),
names and labels, and running commands in ccrp's systemd containers (clones and simulated
robots): the Docker backend's client. DockerProvider builds the clone lifecycle on it; simulated robots of cloud fleets use it
alone (they run here, whatever cloud their clones are on)."""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ...errors import CcrpError
from ...retry import Backoff, ErrorClass, call
from ...store import FleetStore
from ...transport import EXEC_OUTPUT_MAX, too_much
from ..base import LABEL_FLEET, LABEL_ROBOT, LABEL_ROLE
from .archive import tar_files


def _client():
    from ..sdk import docker_module

    try:
        docker = docker_module()
        from docker.errors import DockerException
    except ImportError:  # pragma: no cover - docker is a core dependency
        raise CcrpError("the Docker SDK is not installed", hint="pip install 'ccrp[docker]'") from None
    try:
        client = docker.from_env(timeout=300)
        client.ping()
    except DockerException as exc:
        raise CcrpError(
            f"cannot reach the Docker engine ({type(exc).__name__})",
            hint="start it (`systemctl start docker` or `dockerd &`) and check DOCKER_HOST",
        ) from None
    return client


def engine_answers() -> bool:
    """Whether this host's Docker engine answers a ping (the SDK installed, DOCKER_HOST reachable)."""
    try:
        _client().close()
    except CcrpError:
        return False
    return True


class _EngineBusy(Exception):
    """The engine (or a proxy in front of it) shed load: 429 / 503."""


def _classify(exc: BaseException) -> ErrorClass:
    return ErrorClass.RETRYABLE if isinstance(exc, _EngineBusy) else ErrorClass.FATAL

class DockerHost:
    backoff = Backoff()

    def __init__(self, fleet: str, state_dir: Path | None = None) -> None:
        self.fleet = fleet
        # The fleet's state directory (the store's root): its id labels the snapshot images, so
        # `ccrp gc` can tell whose they are.
        self.state_dir = state_dir or FleetStore(fleet).root
        self.engine = _client()  # docker-py's DockerClient
        from docker.errors import APIError, NotFound

        self.NotFound, self.APIError = NotFound, APIError
        self._retry_busy()

    def _retry_busy(self) -> None:
        """Every Docker API request goes through retry.call: 429/503 answers are retried like a
        cloud's throttling. Other errors (404, 409, 500) are real answers and pass through."""
        api, send = self.engine.api, self.engine.api.send

        def once(request, **kwargs):
            response = send(request, **kwargs)
            if response.status_code in (429, 503):
                raise _EngineBusy(f"HTTP {response.status_code}")
            return response

        def retried(request, **kwargs):
            what = f"Docker API {request.method} {request.path_url.split('?')[0]}"
            return call(once, request, classify=_classify, what=what, backoff=self.backoff, **kwargs)

        api.send = retried  # requests.Session.send: under every docker-py call
    # -- names ------------------------------------------------------------------------------
    @property
    def public_net(self) -> str:
        return f"{self.fleet}-public"

    @property
    def common_net(self) -> str:
        return f"{self.fleet}-common"

    def container_name(self, robot: str, role: str = "clone") -> str:
        return f"ccrp-{self.fleet}-" + {"clone": f"cri-{robot}", "power-sim": f"{robot}-power"}.get(role, robot)

    def volume_name(self, robot: str) -> str:
        return f"ccrp-{self.fleet}-cri-{robot}-vpn"

    def filters(self, role: str, robot: str | None = None) -> dict[str, Any]:
        labels = [f"{LABEL_FLEET}={self.fleet}", f"{LABEL_ROLE}={role}"]
        if robot:
            labels.append(f"{LABEL_ROBOT}={robot}")
        return {"label": labels}
    def container(self, robot: str, role: str = "clone"):
        found = self.engine.containers.list(all=True, ignore_removed=True, filters=self.filters(role, robot))
        return found[0] if found else None

    # -- transport ----------------------------------------------------------------------------
    def running_container(self, robot: str, role: str = "clone"):
        # By name, one request (a label query lists, then inspects): every command in a clone
        # asks first. The labels still decide whether the container is ours.
        try:
            c = self.engine.containers.get(self.container_name(robot, role))
        except self.NotFound:
            c = None
        if c is not None and (c.labels.get(LABEL_FLEET), c.labels.get(LABEL_ROLE), c.labels.get(LABEL_ROBOT)) != (self.fleet, role, robot):
            c = None
        if c is None or c.status != "running":
            what = {"clone": "clone", "power-sim": "simulated power device"}.get(role, "simulated robot")
            raise CcrpError(f"{what} of robot {robot!r} is not running", hint=f"ccrp {'clone create' if role == 'clone' else 'robot sim'} --robot {robot}")
        return c

    def exec(self, robot: str, argv: list[str], timeout: float = 60, role: str = "clone") -> tuple[int, str]:
        c = self.running_container(robot, role)
        api, where = self.engine.api, f"the {role} container of robot {robot!r}"
        # exec_run would read the whole output, however much: stream it and stop at the cap (the
        # command's `timeout` then ends it in the container).
        run = api.exec_create(c.id, ["timeout", str(int(timeout)), *argv])["Id"]
        stream = api.exec_start(run, stream=True)
        out = bytearray()
        try:
            for chunk in stream:
                out += chunk
                if len(out) > EXEC_OUTPUT_MAX:
                    raise CcrpError(too_much(" ".join(argv), where))
        finally:
            stream.close()
        # The engine records the exit status just after the output ends; the stream also ends
        # quietly when its socket times out, the command still running.
        deadline = time.monotonic() + 5
        while (done := api.exec_inspect(run))["Running"] and time.monotonic() < deadline:
            time.sleep(0.05)
        if done["Running"]:
            raise CcrpError(f"`{' '.join(argv)[:120]}` in {where} stopped answering and still runs")
        return done["ExitCode"], out.decode(errors="replace")

    def wait_systemd(self, robot: str, role: str = "clone", timeout: float = 60) -> None:
        """Until systemd inside the container has finished booting."""
        from ...retry import PollTimeout, poll

        def booted() -> tuple[bool, str]:
            _rc, out = self.exec(robot, ["systemctl", "is-system-running", "--wait"], timeout=timeout, role=role)
            return out.strip() in ("running", "degraded"), out.strip()

        try:
            poll(booted, timeout=timeout, interval=0.2)
        except PollTimeout as late:
            raise CcrpError(f"systemd did not come up in {self.container_name(robot, role)}: {str(late.last)[:200]}") from None

    def push_files(self, robot: str, files: Sequence, restart: Sequence[str] = (), role: str = "clone") -> None:
        """Copy bundle files to their `dest` with their modes; chgrp where a group is named."""
        c = self.running_container(robot, role)
        by_dir: dict[str, list] = {}
        for f in files:
            directory, _, name = f.dest.rpartition("/")
            by_dir.setdefault(directory, []).append((name, f.content.encode(), f.mode))
        for directory, entries in by_dir.items():
            c.put_archive(directory, tar_files(entries))
        # One command per group and one for the restarts: each is a round trip (and a runc exec).
        groups: dict[str, list[str]] = {}
        for f in files:
            if f.group != "root":
                groups.setdefault(f.group, []).append(f.dest)
        for group, paths in groups.items():
            self._check(c, ["chgrp", group, *paths])
        if restart:
            self._check(c, ["systemctl", "restart", *restart])

    def _check(self, c, argv: list[str]) -> str:
        result = c.exec_run(argv)
        if result.exit_code != 0:
            raise CcrpError(f"{' '.join(argv)} failed in {c.name}: {result.output.decode(errors='replace').strip()[:200]}")
        return result.output.decode(errors="replace")


class EngineTransport:
    """base.Transport through the engine: commands run as engine execs and files go in as archive
    uploads, into the fleet's containers of one role (DockerProvider's: its clones), with no login
    or session to keep."""

    def __init__(self, host: DockerHost, role: str = "clone") -> None:
        self.host, self.role = host, role

    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        return self.host.exec(robot, argv, timeout=timeout, role=self.role)

    def push_files(self, robot: str, files, restart=()) -> None:
        self.host.push_files(robot, files, restart, role=self.role)
