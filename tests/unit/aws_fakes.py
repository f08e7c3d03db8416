"""moto for the AWS unit and CLI tests: an in-process mock, or a moto server on loopback for
`ccrp` run as a subprocess (boto3 finds it through AWS_ENDPOINT_URL). The fixtures (aws_env,
moto_server, moto_url) are in conftest.py."""

from __future__ import annotations

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
