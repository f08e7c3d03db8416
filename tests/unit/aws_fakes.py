"""moto for the AWS unit and CLI tests: an in-process mock, or a moto server on loopback for
`ccrp` run as a subprocess (boto3 finds it through AWS_ENDPOINT_URL)."""

from __future__ import annotations

import pytest

REGION = "us-east-1"


def inject_error(client, operation: str, code: str, message: str, when=lambda params: True, status: int = 400):
    """Answer the next matching `operation` call with an AWS error, before it reaches the fake."""
    from botocore.awsrequest import AWSResponse

    armed = [True]

    def before(params, **_):
        if armed[0] and when(params.get("body") or {}):
            armed[0] = False
            return (AWSResponse("https://ec2.amazonaws.com/", status, {}, None),
                    {"Error": {"Code": code, "Message": message}, "ResponseMetadata": {"HTTPStatusCode": status}})
        return None

    client.meta.events.register(f"before-call.ec2.{operation}", before)


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
