"""AWS backend (boto3): clones are EC2 instances in the fleet's VPC; see provider.py."""

from ..base import Ability, ProviderInfo
from .settings import AwsSettings

INFO = ProviderInfo(
    kind="aws",
    settings=AwsSettings,
    factory="aws.provider:AwsProvider",
    abilities=frozenset({Ability.BAKE, Ability.CONSOLE}),
    user_data_limit=16_384,  # EC2: 16 KiB before base64
    user_data_gzip=True,
    sdk_modules=(("boto3", "aws"), ("paramiko", "aws")),
)


def __getattr__(name: str):
    # The provider class (and with it the SDK glue) only when asked for by name.
    if name == "AwsProvider":
        from .provider import AwsProvider

        return AwsProvider
    raise AttributeError(name)
