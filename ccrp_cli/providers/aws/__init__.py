"""AWS backend (boto3): clones are EC2 instances in the fleet's VPC; see provider.py."""

from ..base import Ability, InitSection, ProviderInfo
from .settings import AwsSettings

INFO = ProviderInfo(
    kind="aws",
    settings=AwsSettings,
    factory=".aws.provider:AwsProvider",
    abilities=frozenset({Ability.BAKE, Ability.ENTRY_GATEWAY}),
    user_data_limit=16_384,  # EC2: 16 KiB before base64
    user_data_gzip=True,
    sdk_modules=(("boto3", "aws"), ("paramiko", "aws")),
    quota_hint="raise it in the Service Quotas console",
    # The public SSM parameter Debian publishes its current AMI under (AwsProvider.resolve_image).
    bake_base="/aws/service/debian/release/bookworm/latest/amd64",
    bake_base_hint="pass --base-image with a Debian 12 AMI id of the region: `aws ssm get-parameter --name "
                   "/aws/service/debian/release/bookworm/latest/amd64`",
    init=InitSection(
        "  kind: aws\n"
        "  region: eu-west-2\n"
        "  instance_type: t3.medium\n"
        "  zones: [eu-west-2a, eu-west-2b]\n"
        "  operator_cidr: 203.0.113.0/24 # SSH to clones only from here: put your own address range"),
)
