"""Typed values parsed from free-form input before anything is rendered from them.

Every string that ends up in a rendered file (an OpenVPN profile, a Dockerfile, user-data) or in a
cloud API call is one of these, so a newline, a quote or a space in the input is refused with one
line instead of becoming an extra directive in a file root runs on a robot.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass
from typing import Annotated

from pydantic import AfterValidator, BeforeValidator, Field

from ..errors import shown

# Integers are strict: YAML's `true` is not port 1, and "1194" is not a number.
StrictInt = Annotated[int, Field(strict=True)]
Port = Annotated[int, Field(strict=True, ge=1, le=65535)]

_DURATION_RE = re.compile(r"([0-9]{1,6})([smhd])", re.ASCII)
_UNIT = {"s": 1, "m": 60, "h": 3600, "d": 86400}


def _seconds(value: object) -> object:
    """"30m", "90s", "2h", "1d" -> seconds. A bare number is refused: 30 could mean seconds or minutes."""
    if isinstance(value, str):
        m = _DURATION_RE.fullmatch(value.strip())
        if not m:
            raise ValueError(f"{shown(value)} is not a duration: write it as 90s, 30m, 2h or 1d")
        return int(m.group(1)) * _UNIT[m.group(2)]
    if isinstance(value, int) and not isinstance(value, bool):
        raise ValueError(f"{value} has no unit: write it as {value}s or {value}m")
    return value


def parse_duration(text: str, what: str) -> int:
    """A command-line duration (10m, 2h, 1d) in seconds, or one line naming the option."""
    from ..errors import InputError

    try:
        return int(_seconds(text))  # type: ignore[call-overload]
    except ValueError as exc:
        raise InputError(f"{what}: {exc}") from None


# Seconds, written with a unit in the inventory; `never` is 0.
Duration = Annotated[int, BeforeValidator(lambda v: 0 if v == "never" else _seconds(v)), Field(strict=True)]

_SIZE_RE = re.compile(r"([0-9]{1,9}) ?(B|[KMGT]i?B)", re.ASCII)
_SIZE_UNIT = {"B": 1, "KB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
              "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30, "TiB": 1 << 40}


def _bytes(value: object) -> object:
    """"500MB", "2GiB", "64 KiB" -> bytes (KB, MB... are powers of 1000, KiB, MiB... of 1024). A
    bare number is refused: 500 could mean bytes or megabytes."""
    if isinstance(value, str):
        m = _SIZE_RE.fullmatch(value.strip())
        if not m:
            raise ValueError(f"{shown(value)} is not a size: write it as 500MB, 2GiB or 64KiB")
        return int(m.group(1)) * _SIZE_UNIT[m.group(2)]
    if isinstance(value, int) and not isinstance(value, bool):
        raise ValueError(f"{value} has no unit: write it as {value}MB or {value}MiB")
    return value


# Bytes, written with a unit in the inventory.
Size = Annotated[int, BeforeValidator(_bytes), Field(strict=True)]

# -- hosts and endpoints ------------------------------------------------------------------------

_LABEL = r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)"
_HOSTNAME_RE = re.compile(rf"{_LABEL}(?:\.{_LABEL})*\.?", re.ASCII)
_PORT_RE = re.compile(r"[0-9]{1,5}", re.ASCII)


@dataclass(frozen=True)
class Endpoint:
    """Where a robot dials its clone's VPN. `host` is a DNS name, an IPv4 or a bare IPv6 address,
    exactly as OpenVPN's `remote HOST PORT` takes it."""

    host: str
    port: int

    def __str__(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"


def parse_host(text: str) -> str:
    """A DNS name, an IPv4 address or an IPv6 address (without brackets or zone); returned as written."""
    if ":" in text:
        try:
            ipaddress.IPv6Address(text)
        except ValueError:
            raise ValueError(f"{shown(text)} is not an IPv6 address") from None
        if "%" in text:  # a zone (fe80::1%eth0) names an interface of this host, not the robot's
            raise ValueError(f"{shown(text)}: an IPv6 zone is not accepted")
        return text
    if len(text) > 253 or not _HOSTNAME_RE.fullmatch(text):
        raise ValueError(f"{shown(text)} is not a host name or IP address")
    return text


def parse_port(text: str) -> int:
    if not _PORT_RE.fullmatch(text) or not 1 <= int(text) <= 65535:
        raise ValueError(f"port {shown(text)} is not a number from 1 to 65535")
    return int(text)


def parse_endpoint(text: str, default_port: int) -> Endpoint:
    """HOST, HOST:PORT, IPV6, [IPV6] or [IPV6]:PORT (ValueError otherwise)."""
    if text.startswith("["):
        inner, closed, rest = text[1:].partition("]")
        if not closed or (rest and not rest.startswith(":")):
            raise ValueError(f"{shown(text)} is not HOST[:PORT] or [IPV6]:PORT")
        return Endpoint(parse_host(inner), parse_port(rest[1:]) if rest else default_port)
    if text.count(":") > 1:  # a bare IPv6 address: no port can follow it without brackets
        return Endpoint(parse_host(text), default_port)
    host, colon, port = text.partition(":")
    return Endpoint(parse_host(host), parse_port(port) if colon else default_port)


def _endpoint_text(text: str) -> str:
    parse_endpoint(text, 1)
    return text


# An endpoint kept as text (state.json): checked when read, parsed where it is rendered.
EndpointText = Annotated[str, AfterValidator(_endpoint_text)]

# -- image references and cloud names -----------------------------------------------------------

# Docker's reference grammar (distribution/reference): [domain[:port]/]path[:tag][@digest].
_DOMAIN = r"(?:[A-Za-z0-9]|[A-Za-z0-9][A-Za-z0-9-]*[A-Za-z0-9])(?:\.(?:[A-Za-z0-9]|[A-Za-z0-9][A-Za-z0-9-]*[A-Za-z0-9]))*(?::[0-9]+)?"
_PATH = r"[a-z0-9]+(?:(?:[._]|__|-+)[a-z0-9]+)*"
_TAG = r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}"
_DIGEST = r"[A-Za-z][A-Za-z0-9]*(?:[-_+.][A-Za-z][A-Za-z0-9]*)*:[0-9a-fA-F]{32,}"
_DOCKER_REF_RE = re.compile(rf"(?:{_DOMAIN}/)?{_PATH}(?:/{_PATH})*(?::{_TAG})?(?:@{_DIGEST})?", re.ASCII)

# One token a cloud API takes as a name or id: a Glance image name or uuid, a GCE image path or
# URL, an AMI id or SSM parameter, a region, a zone, a flavor, a network. No space, quote or
# control character can be in it.
_CLOUD_NAME_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9._:/@+=-]{0,254}", re.ASCII)


def check_docker_image(text: str) -> str:
    if len(text) > 255 or not _DOCKER_REF_RE.fullmatch(text):
        raise ValueError(f"{shown(text)} is not a Docker image reference (REGISTRY/NAME:TAG)")
    return text


def check_cloud_name(text: str) -> str:
    if not _CLOUD_NAME_RE.fullmatch(text):
        raise ValueError(f"{shown(text)} is not a cloud name or id "
                         "(letters, digits and . _ : / @ + = -, at most 255 characters)")
    return text


DockerImage = Annotated[str, AfterValidator(check_docker_image)]
CloudName = Annotated[str, AfterValidator(check_cloud_name)]
