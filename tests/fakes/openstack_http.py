"""A FakeOpenStack served over real HTTP on 127.0.0.1, for clients in other processes (the ccrp
CLI run as a subprocess, plain openstacksdk).

Each service lives under a path of the served root: http://127.0.0.1:PORT/identity (Keystone v3),
/compute/v2.1/ (Nova), /network (Neutron), /image (Glance). Keystone's token carries a catalog of
those URLs (built like openstacksdk's ConnectionFixture builds its own, for the served root), and
the version documents point there too. Requests go to the same handler as the in-process
requests-mock transport (FakeOpenStack.handle). One thread per connection (ThreadingHTTPServer),
HTTP/1.1 keep-alive.

    with OpenStackHttp(FakeOpenStack(boot=CloudBoot())) as served:
        config = served.clouds_yaml(tmp_path, "fake")   # OS_CLIENT_CONFIG_FILE=config
        ...

or, servers booting and everything of the run removed at the end (`booting_cloud`):

    with booting_cloud(tmp_path, "fake") as served:
        subprocess.run(["ccrp", "fleet", "up", "-i", inventory], env={**os.environ, **served.environ()})
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import urlsplit

from .openstack_cloud import HOSTS, Context, FakeOpenStack


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_version = "ccrp-fake-openstack"
    fake: FakeOpenStack
    root: str

    def _serve(self) -> None:
        url = urlsplit(self.path)
        service, _, rest = url.path.lstrip("/").partition("/")
        length = int(self.headers.get("Content-Length") or 0)
        body = self.rfile.read(length) if length else b""
        context = Context()
        if service not in HOSTS:
            context.status_code, answer = 404, {"error": {"code": 404, "message": f"no service at {url.path}"}}
        else:
            try:
                answer = self.fake.handle(self.command, service, "/" + rest, url.query, body, context, root=self.root)
            except Exception as exc:  # noqa: BLE001 - a fake's bug is a 500 for the client, not a dead socket
                context.status_code, answer = 500, {"error": {"code": 500, "message": f"{type(exc).__name__}: {exc}"}}
        data = b"" if answer is None or context.status_code == 204 else json.dumps(answer).encode()
        self.send_response(context.status_code)
        for key, value in context.headers.items():
            if key.lower() != "content-length":
                self.send_header(key, value)
        if "Content-Type" not in context.headers:
            self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(data)

    do_GET = do_POST = do_PUT = do_DELETE = do_PATCH = do_HEAD = _serve

    def log_message(self, format, *args) -> None:
        pass  # quiet: FakeOpenStack.calls counts what was asked


class OpenStackHttp:
    """Serve `fake` on 127.0.0.1 (a free port unless given) in a thread of this process."""

    def __init__(self, fake: FakeOpenStack, port: int = 0) -> None:
        self.fake = fake
        handler = type("Handler", (_Handler,), {"fake": fake})
        self.httpd = ThreadingHTTPServer(("127.0.0.1", port), handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.url = f"http://127.0.0.1:{self.port}"
        handler.root = self.url
        self._thread: threading.Thread | None = None
        self.config_path: Path | None = None

    @property
    def auth_url(self) -> str:
        return f"{self.url}/identity"

    def start(self) -> OpenStackHttp:
        if self._thread is None:
            self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.2},
                                            name=f"fake-openstack-http-{self.port}", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        if self._thread is not None:
            self.httpd.shutdown()
            self._thread.join()
            self._thread = None
        self.httpd.server_close()

    def __enter__(self) -> OpenStackHttp:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def cloud_config(self) -> dict:
        """One clouds.yaml entry for this server (password auth; the fake accepts any)."""
        return {"auth": {"auth_url": self.auth_url, "username": "admin", "password": "password",
                         "project_name": "admin", "user_domain_name": "default", "project_domain_name": "default"},
                "region_name": "RegionOne", "identity_api_version": "3", "interface": "public"}

    def clouds_yaml(self, directory: Path, cloud: str) -> Path:
        """directory/clouds.yaml with `cloud` pointing here: OS_CLIENT_CONFIG_FILE=<it> and
        `openstack.connect(cloud=...)` or `ccrp` with provider.cloud = `cloud`."""
        path = Path(directory) / "clouds.yaml"
        path.write_text(json.dumps({"clouds": {cloud: self.cloud_config()}}, indent=2) + "\n")
        self.config_path = path
        return path

    def environ(self) -> dict[str, str]:
        """The environment for a client process: the clouds.yaml written last, no secure.yaml,
        and every OS_* variable of this process blanked (openstacksdk would merge them in)."""
        env = {k: "" for k in os.environ if k.startswith("OS_")}
        env["OS_CLIENT_CONFIG_FILE"] = str(self.config_path)
        env["OS_CLIENT_SECURE_FILE"] = str(self.config_path.parent / "no-secure.yaml")
        return env


@contextmanager
def booting_cloud(directory: Path, cloud: str = "ccrp-fake", run_id: str | None = None,
                  **fake_options) -> Iterator[OpenStackHttp]:
    """A FakeOpenStack whose servers boot (cloudboot), served on 127.0.0.1, its clouds.yaml in
    `directory` for `cloud`; on exit the server stops and every container, network and image of
    the run is removed, whatever happened. `fake_options`: FakeOpenStack's (fip_cidr, vendor_data).
    The served object has .fake (fip_network, fip_cidr, servers...) and .fake.boot (CloudBoot)."""
    from .cloudboot import CloudBoot

    boot = CloudBoot(run_id)
    fake = None
    try:
        boot.base_image()  # built once per machine (about a minute), before any client waits on it
        fake = FakeOpenStack(boot=boot, **fake_options)
        with OpenStackHttp(fake) as served:
            served.clouds_yaml(directory, cloud)
            yield served
    finally:
        if fake is not None:
            fake.wait_idle(30)  # a boot under way finishes (or fails) before the sweep
        boot.cleanup()          # and whatever a thread still creates after it is removed at once
        boot.client.close()
