"""The AWS harness against moto's server in a process of its own (for bench/provision_clouds.py).

harness_aws.py runs moto in-process (mock_aws): moto's CPU shares the GIL with ccrp's worker
threads, and its lock lets one request at a time into moto. Here moto is `python -m moto.server`
on 127.0.0.1 and a free port, a child process started for each harness and always killed when
it closes. AwsProvider is not changed: its boto3 client is sent there by the environment
(AWS_ENDPOINT_URL, honoured by botocore >= 1.31, with dummy credentials) while the provider is
built. The call counting, the injected delay and the faults are harness_aws.py's own botocore
hooks, client-side, before a request leaves; only the harness's lock around moto is dropped, as
the fake is now another process. Responses with a 5xx status are counted in `server_errors`: an
EC2 error (XML, InternalError and the like) is retried by ccrp's retry.call, every retry counted
in `calls` like any call; a 500 from an exception inside moto comes as an HTML page, which
botocore cannot parse (ResponseParserError): ccrp retries that too (providers/aws/errors.py).

`threaded`: moto.server's stock werkzeug server takes each connection on a thread of its own;
threaded=False serves one request at a time (the fake serialised in its own process only).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

from .harness_aws import REGION, AwsHarness
from .specs import FAST, OPERATOR_CIDR, inventory

# moto.server's own main, with werkzeug's threaded switch off.
SINGLE_THREADED = """
import sys
from werkzeug.serving import run_simple
from moto.moto_server.werkzeug_app import DomainDispatcherApplication, MotoRequestHandler, create_backend_app
run_simple(sys.argv[1], int(sys.argv[2]), DomainDispatcherApplication(create_backend_app),
           threaded=False, request_handler=MotoRequestHandler)
"""


class _NoLock:
    """Stands in for AwsHarness's lock around in-process moto: the server is another process."""

    def acquire(self) -> bool:
        return True

    def release(self) -> None:
        pass


class AwsServerHarness(AwsHarness):
    # kind stays "aws": the contract suite's per-cloud expectations hold here as well.

    def __init__(self, provider, raw, server: "MotoServer") -> None:
        super().__init__(provider, raw)
        self._moto = _NoLock()
        self.server = server
        self.server_errors: Counter = Counter()
        # Before botocore parses the answer: moto's server answers an exception of its own with a
        # 500 and an HTML page, which botocore cannot parse (ResponseParserError, not a ClientError).
        # Only the server's answers pass here: a throttle injected by throttle() never reached it.
        provider.client.ec2.meta.events.register("before-parse.ec2", self._count_5xx)

    def _count_5xx(self, operation_model, response_dict, **_):
        if response_dict["status_code"] >= 500:
            with self._lock:
                self.server_errors[f"{operation_model.name} {response_dict['status_code']}"] += 1

    def new_provider(self, inv, workdir):
        """An AwsProvider of another inventory on the same server (built in the server's
        environment, as make_harness builds the first), its 5xx answers counted too."""
        with server_env(self.server.url, Path(workdir)):
            provider = super().new_provider(inv, workdir)
        provider.client.ec2.meta.events.register("before-parse.ec2", self._count_5xx)
        return provider

    def fake_cpu(self) -> float:
        """CPU seconds (user + system) the moto server process has used so far."""
        return self.server.cpu_seconds()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class MotoServer:
    def __init__(self, log: Path, threaded: bool = True) -> None:
        self.port = _free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = log
        args = ["-m", "moto.server", "-H", "127.0.0.1", "-p"] if threaded else ["-c", SINGLE_THREADED, "127.0.0.1"]
        self._out = open(log, "wb")
        try:
            self.proc = subprocess.Popen([sys.executable, *args, str(self.port)], stdout=self._out,
                                         stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
        except BaseException:
            self._out.close()
            raise

    def wait_ready(self, timeout: float = 60.0) -> None:
        deadline = time.perf_counter() + timeout
        while time.perf_counter() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"moto server exited ({self.proc.returncode}): {self.log_tail()}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=1):
                    return
            except OSError:
                time.sleep(0.1)
        raise RuntimeError(f"moto server not listening on {self.url} after {timeout:.0f} s: {self.log_tail()}")

    def cpu_seconds(self) -> float:
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime

    def status_counts(self) -> Counter:
        """HTTP statuses in werkzeug's request log ("POST / HTTP/1.1" 200 -)."""
        self._out.flush()
        counts: Counter = Counter()
        for line in self.log.read_text(errors="replace").splitlines():
            parts = line.split('" ')
            if len(parts) > 1 and parts[-1][:3].isdigit():
                counts[parts[-1][:3]] += 1
        return counts

    def log_tail(self, n: int = 20) -> str:
        self._out.flush()
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])

    def stop(self) -> None:
        try:
            if self.proc.poll() is None:
                self.proc.terminate()
                try:
                    self.proc.wait(10)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        finally:
            self._out.close()


@contextmanager
def server_env(url: str, tmp: Path):
    """os.environ as botocore reads it when a client is built: the server's URL, dummy credentials,
    none of the variables that would override them; restored on exit."""
    empty = tmp / "aws-config"  # not /dev/null: where it is a regular file, it is not empty
    tmp.mkdir(parents=True, exist_ok=True)
    empty.write_text("")
    env = {"AWS_ENDPOINT_URL": url, "AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
           "AWS_DEFAULT_REGION": REGION, "AWS_CONFIG_FILE": str(empty), "AWS_SHARED_CREDENTIALS_FILE": str(empty)}
    with mock.patch.dict(os.environ, env):
        for var in ("AWS_SESSION_TOKEN", "AWS_PROFILE", "AWS_IGNORE_CONFIGURED_ENDPOINT_URLS"):
            os.environ.pop(var, None)
        yield


@contextmanager
def make_harness(tmp_path, threaded: bool = True):
    import boto3

    from ccrp_cli.providers.aws.provider import AwsProvider

    inv = inventory({"kind": "aws", "region": REGION, "zones": ["us-east-1a", "us-east-1b"],
                     "instance_type": "t3.medium", "operator_cidr": OPERATOR_CIDR,
                     # the contract proves clones at their own addresses; the gateway: test_aws_provider.py
                     "entry": "per-clone"})
    server = MotoServer(Path(tmp_path) / "moto-server.log", threaded=threaded)
    try:
        server.wait_ready()
        # Only while the clients are built: botocore reads the endpoint and credentials then.
        with server_env(server.url, Path(tmp_path)):
            provider = AwsProvider(inv, Path(tmp_path) / "store")
            raw = boto3.Session(region_name=REGION).client("ec2")
        for client in (provider.client.ec2, raw):
            if client.meta.endpoint_url != server.url:
                raise RuntimeError(f"boto3 client not sent to the moto server: {client.meta.endpoint_url}")
        provider.client.backoff = FAST
        provider.bootstrap()
        yield AwsServerHarness(provider, raw, server)
    finally:
        server.stop()


if __name__ == "__main__":  # a quick check by hand: one clone on the server
    from .specs import ROBOTS

    with tempfile.TemporaryDirectory() as tmp, make_harness(Path(tmp)) as h:
        print(h.provider.run_instance(h.spec(ROBOTS[0], 1)), h.instances_for(ROBOTS[0]), h.api_calls(),
              h.server_errors, h.server.status_counts(), f"{h.fake_cpu():.2f} s CPU", threading.active_count())
