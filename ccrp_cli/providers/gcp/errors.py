"""What a google-cloud-compute failure means: retry, next zone, not in this region, or fatal;
and the one-line CcrpError the user sees."""

from __future__ import annotations

import re

from ...errors import CcrpError
from ...retry import ErrorClass

# Codes GCE puts in operation errors (error.errors[].code) or HTTP errors (errors[].reason).
# Stock-outs and their messages: "Troubleshoot resource availability errors" in the Compute
# Engine docs (the zone's pool of that machine shape is empty; another zone may have it).
ZONE_CODES = {
    "ZONE_RESOURCE_POOL_EXHAUSTED", "ZONE_RESOURCE_POOL_EXHAUSTED_WITH_DETAILS", "RESOURCE_POOL_EXHAUSTED",
    "GPU_STOCKOUT", "insufficientCapacity",
}
ZONE_TEXT = re.compile(r"does not have enough resources available|is currently unavailable in the \S+ zone", re.I)
# Transient: rate limits, the per-project limit on operations in flight, and a resource that
# another operation is still changing (e.g. the network while a route is added).
RATE_CODES = {"rateLimitExceeded", "userRateLimitExceeded", "RATE_LIMIT_EXCEEDED",
              "CONCURRENT_OPERATIONS_QUOTA_EXCEEDED", "resourceNotReady", "RESOURCE_NOT_READY"}
# Quotas are per region (CPUS, IN_USE_ADDRESSES...) or per project: no zone helps.
QUOTA_CODES = {"QUOTA_EXCEEDED", "quotaExceeded", "REGION_RESOURCE_POOL_EXHAUSTED"}
# HTTP status classes worth the same call again (api_core exception class names).
RETRYABLE_TYPES = ("TooManyRequests", "ServiceUnavailable", "InternalServerError", "ServerError",
                   "GatewayTimeout", "DeadlineExceeded", "BadGateway")
# requests / google.auth transport failures (connection reset, read timeout) are worth a retry too.
TRANSPORT_TYPES = ("ConnectionError", "Timeout", "ChunkedEncodingError", "TransportError")

LOGIN_HINT = ("run `gcloud auth application-default login` (or set GOOGLE_APPLICATION_CREDENTIALS); "
              "the account needs Compute Admin on the project")


def reasons(exc: BaseException) -> set[str]:
    """Machine-readable codes of an api_core error: operation errors are compute_v1.Errors
    (.code), HTTP errors are dicts ({"reason": ...}); ErrorInfo gives .reason."""
    found = set()
    for item in getattr(exc, "errors", None) or []:
        for key in ("code", "reason"):
            value = item.get(key) if isinstance(item, dict) else getattr(item, key, None)
            if isinstance(value, str) and value:
                found.add(value)
    reason = getattr(exc, "reason", None)
    if isinstance(reason, str) and reason:
        found.add(reason)
    return found


def _is(exc: BaseException, names: tuple[str, ...]) -> bool:
    return any(cls.__name__ in names for cls in type(exc).__mro__)


def classify(exc: BaseException) -> ErrorClass:
    # Codes first: a stock-out arrives as 503 and a rate limit as 403, so the HTTP class misleads.
    codes = reasons(exc)
    if codes & ZONE_CODES or ZONE_TEXT.search(str(exc)):
        return ErrorClass.ZONE
    if codes & RATE_CODES:  # before quotas: the operations limit is called a quota too
        return ErrorClass.RETRYABLE
    if codes & QUOTA_CODES:
        return ErrorClass.REGION
    if _is(exc, RETRYABLE_TYPES + TRANSPORT_TYPES):
        return ErrorClass.RETRYABLE
    return ErrorClass.FATAL


def as_ccrp_error(what: str, exc: BaseException, region: str) -> CcrpError:
    """One line for any SDK failure, with the hint that fits its class."""
    if isinstance(exc, CcrpError):
        return exc
    text = " ".join(str(getattr(exc, "message", "") or exc).split())[:200]
    codes = sorted(reasons(exc) - {""})
    detail = f"{type(exc).__name__}{' ' + ','.join(codes) if codes else ''}: {text}"
    kind = classify(exc)
    if kind is ErrorClass.REGION:
        return CcrpError(f"{what}: GCE quota exceeded in {region} ({detail})",
                         hint=f"request more quota for {region} (console: IAM & Admin > Quotas), delete unused "
                              "instances, or pick another region; `ccrp doctor` shows current usage")
    if kind is ErrorClass.ZONE:
        return CcrpError(f"{what}: no capacity ({detail})",
                         hint="add zones to provider.zones or pick another machine type")
    if _is(exc, ("Unauthorized", "Unauthenticated", "Forbidden", "PermissionDenied", "RefreshError")):
        return CcrpError(f"{what}: not allowed ({detail})", hint=LOGIN_HINT)
    if _is(exc, ("Conflict", "AlreadyExists")):
        return CcrpError(f"{what}: name taken ({detail})",
                         hint="a resource with ccrp's name exists without the fleet's ownership marks; rename or remove it")
    if _is(exc, ("NotFound",)):
        return CcrpError(f"{what}: not found ({detail})",
                         hint="check provider.project, region, zones, machine_type and the snapshot name")
    return CcrpError(f"{what}: {detail}")
