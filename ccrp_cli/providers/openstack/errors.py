"""What an OpenStack failure means for ccrp: retry, next zone, give up on the region, or fatal;
and the one line the user reads. openstacksdk / keystoneauth are imported here only lazily."""

from __future__ import annotations

import re

from ...errors import CcrpError
from ...retry import ErrorClass

RETRYABLE_STATUS = {429, 500, 502, 503, 504}
# Nova's scheduler and the hypervisors word "this zone is full" in several ways.
CAPACITY = re.compile(r"no valid host|not enough hosts|insufficient|capacity|availability zone .* not available", re.I)
# Nova's words when the scheduler found hosts but the build failed on each (the compute host's fault:
# a config drive it could not write, an image it could not boot). Another zone's hosts may build it,
# so it moves on as for capacity, but the user is told the cause is on the cloud's side: met on a
# real Nova (docs/openstack.md, difference 3), where "no capacity" sent users the wrong way.
BUILD_FAILED = re.compile(r"exhausted all hosts|exceeded maximum number of retries", re.I)
BUILD_HINT = ("the cloud's compute hosts failed to build it (not a lack of capacity): ask the cloud's admin, whose "
              "nova-compute log says why, or try another image or flavor")
# Nova's answer (400) to a server whose image is not in Glance (deleted after ccrp looked it up).
IMAGE_GONE = re.compile(r"can not find requested image", re.I)
IMAGE_HINT = "ccrp snapshot list / ccrp snapshot build"
UNAUTHORIZED = re.compile(r"\(HTTP 401\)")
QUOTA = re.compile(r"quota|over ?limit|overquota", re.I)
QUOTA_HINT = ("raise the project's quota (`openstack quota show`) or delete servers / floating IPs it "
              "no longer needs")


class ServerFault(Exception):
    """A server went to ERROR; the message is Nova's fault (e.g. "No valid host was found")."""


def status_of(exc: BaseException) -> int | None:
    return getattr(exc, "status_code", None) or getattr(exc, "http_status", None)


def message_of(exc: BaseException) -> str:
    """The cloud's own words, without the SDK's URL boilerplate."""
    details = getattr(exc, "details", None)
    text = str(details) if details else str(getattr(exc, "message", "") or exc)
    return " ".join(text.split())[:300]


def classify(exc: BaseException) -> ErrorClass:
    from keystoneauth1 import exceptions as ksa

    if isinstance(exc, ServerFault):
        return ErrorClass.ZONE if CAPACITY.search(str(exc)) or BUILD_FAILED.search(str(exc)) else ErrorClass.FATAL
    if isinstance(exc, (ksa.ConnectionError, ksa.RetriableConnectionFailure)):
        return ErrorClass.RETRYABLE
    try:
        import requests

        if isinstance(exc, (requests.ConnectionError, requests.Timeout)):
            return ErrorClass.RETRYABLE
    except ImportError:  # pragma: no cover - requests comes with openstacksdk
        pass
    if "does not have any supported versions" in str(exc):
        # Version discovery was throttled or failed (keystoneauth only logs that): the next
        # attribute access discovers again. A cloud truly without the service fails after the retries.
        return ErrorClass.RETRYABLE
    status = status_of(exc)
    text = f"{exc} {getattr(exc, 'details', '') or ''}"
    if status in RETRYABLE_STATUS and not CAPACITY.search(text):
        return ErrorClass.RETRYABLE
    if status in (403, 409, 413) and QUOTA.search(text):
        return ErrorClass.REGION
    if status in (400, 409, 500) and (CAPACITY.search(text) or BUILD_FAILED.search(text)):
        return ErrorClass.ZONE
    return ErrorClass.FATAL


def is_sdk_error(exc: BaseException) -> bool:
    from keystoneauth1.exceptions import ClientException
    from openstack.exceptions import SDKException

    return isinstance(exc, (SDKException, ClientException, ServerFault))


def to_ccrp(what: str, cloud: str, exc: BaseException) -> CcrpError:
    """One line for the user, with the hint that fits the class of failure."""
    kind, status, msg = classify(exc), status_of(exc), message_of(exc)
    if kind is ErrorClass.REGION:
        return CcrpError(f"{what}: quota exceeded on cloud {cloud!r}: {msg}", hint=QUOTA_HINT)
    # Connection.authorize() (`ccrp doctor`) re-raises keystoneauth's 401 as a bare SDKException:
    # only its text says "(HTTP 401)" (met on a real Keystone, docs/openstack.md, differences).
    if status == 401 or type(exc).__name__ in ("Unauthorized", "MissingAuthPlugin", "NoMatchingPlugin") \
            or UNAUTHORIZED.search(msg):
        return CcrpError(f"{what}: cloud {cloud!r} refused the credentials: {msg}",
                         hint=f"check the {cloud!r} entry of clouds.yaml (or OS_CLOUD) and `openstack token issue`")
    if kind is ErrorClass.ZONE and BUILD_FAILED.search(msg):
        return CcrpError(f"{what}: the cloud could not build the server: {msg}", hint=BUILD_HINT)
    if kind is ErrorClass.ZONE:
        return CcrpError(f"{what}: no capacity: {msg}", hint="add zones to the inventory's provider.zones or pick another flavor")
    return CcrpError(f"{what}: {msg or type(exc).__name__}")
