"""AWS backend (boto3): clones are EC2 instances in the fleet's VPC; see provider.py."""

from .provider import AwsProvider

__all__ = ["AwsProvider"]
