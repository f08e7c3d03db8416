"""botocore errors -> retry classes, and -> one-line CcrpErrors for users.

Codes from the EC2 API reference ("Common client error codes", "Server error codes").
"""

from __future__ import annotations

from ...errors import CcrpError
from ...retry import ErrorClass

RETRYABLE = {
    "Throttling", "ThrottlingException", "RequestLimitExceeded", "RequestThrottled",
    "RequestThrottledException", "TooManyRequestsException", "EC2ThrottledException", "SlowDown",
    "InternalError", "InternalFailure", "ServiceUnavailable", "Unavailable", "RequestTimeout",
    "RequestTimeoutException", "PriorRequestNotComplete", "RequestExpired",
}
# The instance type has no capacity in this zone now; another zone may have it.
ZONE = {"InsufficientInstanceCapacity", "InsufficientHostCapacity", "InsufficientCapacity",
        "InsufficientReservedInstanceCapacity"}
# Account quotas are per region: no zone of the region can help.
REGION = {"InstanceLimitExceeded", "VcpuLimitExceeded", "MaxSpotInstanceCountExceeded", "AddressLimitExceeded",
          "VpcLimitExceeded", "SecurityGroupLimitExceeded", "RouteLimitExceeded", "RulesPerSecurityGroupLimitExceeded",
          "InsufficientAddressCapacity", "SubnetLimitExceeded", "InternetGatewayLimitExceeded"}
AUTH = {"AuthFailure", "UnauthorizedOperation", "InvalidClientTokenId", "UnrecognizedClientException",
        "SignatureDoesNotMatch", "OptInRequired", "ExpiredToken"}
INSTALL_HINT = "pip install 'ccrp[aws]'"


def error_code(exc: BaseException | None) -> str:
    response = getattr(exc, "response", None) or getattr(exc, "last_response", None) or {}
    return (response.get("Error") or {}).get("Code", "")


def _status(exc: BaseException) -> int:
    response = getattr(exc, "response", None) or {}
    return int((response.get("ResponseMetadata") or {}).get("HTTPStatusCode") or 0)


def classify(exc: BaseException) -> ErrorClass:
    from botocore.exceptions import ClientError, ConnectionError, HTTPClientError, WaiterError
    from botocore.parsers import ResponseParserError

    if isinstance(exc, CcrpError) and exc.__cause__ is not None:
        return classify(exc.__cause__)  # a translated SDK error keeps its class
    if isinstance(exc, (ConnectionError, HTTPClientError)):
        return ErrorClass.RETRYABLE  # connection reset / timeouts before an answer
    if isinstance(exc, ResponseParserError):
        return ErrorClass.RETRYABLE  # an answer that is not EC2's XML: a proxy's or gateway's 5xx page
    if isinstance(exc, (ClientError, WaiterError)):
        code = error_code(exc)
        # Capacity errors come with HTTP 500 ("server error codes"): name before status.
        if code in ZONE or (code == "Unsupported" and "Availability Zone" in str(exc)):
            return ErrorClass.ZONE
        if code in REGION:
            return ErrorClass.REGION
        if code in RETRYABLE or _status(exc) >= 500:
            return ErrorClass.RETRYABLE
    return ErrorClass.FATAL


def as_ccrp(what: str, exc: BaseException) -> CcrpError:
    """One line for the user; the SDK error stays attached as __cause__ for classify()."""
    if isinstance(exc, CcrpError):
        return exc
    from botocore.exceptions import NoCredentialsError, ProfileNotFound

    code = error_code(exc)
    message = str(exc).split("\n")[0][:300]
    if isinstance(exc, (NoCredentialsError, ProfileNotFound)) or code in AUTH:
        hint = "configure AWS credentials (aws configure, AWS_PROFILE or the inventory's provider.profile); `ccrp doctor` checks them"
    elif code in REGION:
        hint = "an account quota is reached: raise it in Service Quotas or use a smaller fleet; `ccrp doctor` shows quotas"
    elif code in ZONE:
        hint = "AWS has no capacity for this instance type now: retry later or change provider.instance_type"
    else:
        hint = None
    err = CcrpError(f"AWS {what}: {message}", hint=hint)
    err.__cause__ = exc
    return err
