"""Fixtures of the unit tests beyond tests/conftest.py's."""

from __future__ import annotations

import pytest

from ccrp_cli.fleet import Fleet
from tests.conftest import LAB
from tests.unit.aws_fakes import REGION


@pytest.fixture
def lab_up(ccrp_home):
    """The lab fleet with every clone recorded as ready."""
    from ccrp_cli.ops import vpn

    fleet = Fleet.open(LAB)
    vpn.init(fleet)
    state = fleet.load_allocated()
    plan = fleet.plan(state)
    for name, rec in state.robots.items():
        rec.phase = "ready"
        fleet.pki.issue_relay(name, str(plan[name].common_ip), 30)  # as ensure_clone does
    fleet.store.save_state(state)
    return fleet, state


@pytest.fixture
def aws_env(tmp_path, monkeypatch):
    """Fake credentials and no shared config: nothing here can reach a real account."""
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_DEFAULT_REGION", REGION)
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "no-aws-config"))
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "no-aws-credentials"))
    for var in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_ENDPOINT_URL"):
        monkeypatch.delenv(var, raising=False)


@pytest.fixture(scope="module")
def moto_server():
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    try:
        yield f"http://{host}:{port}"
    finally:
        server.stop()


@pytest.fixture
def moto_url(moto_server, aws_env, monkeypatch):
    import requests

    requests.post(f"{moto_server}/moto-api/reset", timeout=10).raise_for_status()
    monkeypatch.setenv("AWS_ENDPOINT_URL", moto_server)
    return moto_server
