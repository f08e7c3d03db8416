"""AWS backend (boto3): clones are EC2 instances in the fleet's VPC; see provider.py."""

from ..base import Ability, ProviderInfo
from .settings import AwsSettings

INFO = ProviderInfo(
    kind="aws",
    settings=AwsSettings,
    factory=".aws.provider:AwsProvider",
    abilities=frozenset({Ability.BAKE}),
    user_data_limit=16_384,  # EC2: 16 KiB before base64
    user_data_gzip=True,
    sdk_modules=(("boto3", "aws"), ("paramiko", "aws")),
    quota_hint="raise it in the Service Quotas console",
    # The public SSM parameter Debian publishes its current AMI under (AwsProvider.resolve_image).
    bake_base="/aws/service/debian/release/bookworm/latest/amd64",
    bake_base_hint="pass --base-image with a Debian 12 AMI id of the region: `aws ssm get-parameter --name "
                   "/aws/service/debian/release/bookworm/latest/amd64`",
)
