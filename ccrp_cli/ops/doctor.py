"""`ccrp doctor`: is this machine and account ready to run the fleet? One row per check, each
with what to do when it fails. Read-only: nothing is created."""

from __future__ import annotations

import importlib.util
import shutil
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, cast

from ..errors import CcrpError
from ..fleet import Fleet
from ..providers.base import CloneState

if TYPE_CHECKING:
    from ..providers.base import Gateways, HostImages, Provider

OK, FAIL, WARN, SKIP = "ok", "fail", "warn", "skip"
# Not needed by ccrp itself; handy for checking its work by hand.
OPTIONAL_TOOLS = {
    "openssl": "inspect and verify the fleet's certificates (openssl verify -crl_check)",
    "ssh-keygen": "compare clone host-key fingerprints by hand",
}


@dataclass
class Check:
    check: str
    status: str  # ok | fail | warn | skip
    detail: str = ""
    hint: str = ""


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # a missing parent package (google.cloud)
        return False


def _failed(name: str, exc: CcrpError) -> Check:
    return Check(name, FAIL, exc.message, exc.hint or "")


def run(fleet: Fleet) -> list[Check]:
    inv = fleet.inventory
    kind = inv.provider.kind
    checks = []
    from ..providers import Ability, info

    sdks = info(kind).sdk_modules  # paramiko: the SSH transport of every cloud
    missing = [(m, extra) for m, extra in sdks if not _installed(m)]
    for module, extra in sdks:
        if (module, extra) in missing:
            checks.append(Check(f"sdk {module}", FAIL, "not installed", f"pip install 'ccrp[{extra}]'"))
        else:
            checks.append(Check(f"sdk {module}", OK, "installed"))
    provider = None
    if not missing:
        provider, check = _provider(fleet)
        checks.append(check)
    if provider is not None:
        checks += _credentials(provider) + _quotas(fleet, provider) + [_snapshot(fleet, provider)]
        if Ability.HOST_IMAGES in provider.abilities:
            checks.append(_snapshot_images(cast("HostImages", provider)))
        if inv.provider.entry == "gateway":
            checks.append(_gateway(fleet, cast("Gateways", provider)))
    if inv.ros.ros2 and not info(kind).own_kernel:
        checks.append(host_receive_buffer())
    for tool, why in info(kind).host_tools:
        if shutil.which(tool) is None:
            checks.append(Check(f"tool {tool}", WARN, "not found", f"apt-get install {tool} ({why})"))
    for tool, why in OPTIONAL_TOOLS.items():
        found = shutil.which(tool)
        checks.append(Check(f"tool {tool}", OK if found else WARN, found or f"not found (optional: {why})",
                            "" if found else f"install {tool} (optional)"))
    return checks


RMEM_DEFAULT = "/proc/sys/net/core/rmem_default"


def host_receive_buffer(path: str = RMEM_DEFAULT) -> Check:
    """ROS 2 clones sharing this host's kernel (containers) get its default UDP receive buffer, which
    no clone can raise for itself (not per network namespace): VM clones get ccrp's from their
    user-data (layout.ROS2_RMEM)."""
    from ..models.layout import ROS2_RMEM

    try:
        have = int(open(path).read())
    except (OSError, ValueError):
        return Check("host rmem_default", SKIP, f"{path} not readable")
    if have >= ROS2_RMEM:
        return Check("host rmem_default", OK, f"{have} bytes")
    return Check("host rmem_default", WARN,
                 f"{have} bytes: ROS 2 subscribers on the clones may drop image datagrams (docs/ros2.md)",
                 f"sysctl -w net.core.rmem_default={ROS2_RMEM} net.core.rmem_max={ROS2_RMEM} (every process of this host)")


def _provider(fleet: Fleet) -> tuple[Provider | None, Check]:
    from ..providers import get_provider, info

    kind = fleet.inventory.provider.kind
    name = f"{kind} {info(kind).reach}"
    try:
        provider = get_provider(fleet.inventory)
    except CcrpError as exc:
        return None, _failed(name, exc)
    if info(kind).reach_is_credential:
        return provider, Check(name, OK, provider.check_credentials())
    return provider, Check(name, OK, f"region/cloud {fleet.inventory.provider.place()}".strip())


def _credentials(provider: Provider) -> list[Check]:
    from ..providers import info

    if info(provider.kind).reach_is_credential:
        return []  # reaching the backend (checked above) was the credential
    try:
        return [Check("credentials", OK, provider.check_credentials())]
    except CcrpError as exc:
        return [_failed("credentials", exc)]


def _quotas(fleet: Fleet, provider: Provider) -> list[Check]:
    """Each quota the fleet's clones draw on: its limit and use now, and what the clones not
    created yet take of it (the numbers `fleet up` checks before it creates anything)."""
    from . import quotas
    from ..providers import info

    try:
        state = fleet.store.load_state()
        missing = quotas.new_clones(fleet, provider, [r.name for r in fleet.members(state)])
        found = quotas.uses(provider, missing)
    except CcrpError as exc:
        return [Check("quotas", WARN, exc.message, exc.hint or "grant read access to quotas to see them")]
    return [
        Check(f"quota {u.quota.name} in {u.quota.scope}", FAIL if u.short else OK,
              f"limit {u.quota.limit:g}, used {u.quota.used:g}; the fleet's {len(missing)} clone(s) not created "
              f"yet need {u.need:g}",
              f"{u.quota.hint or info(provider.kind).quota_hint}, or shrink the fleet"
              if u.short else "")
        for u in found
    ]


def _snapshot(fleet: Fleet, provider: Provider) -> Check:
    recorded = (fleet.store.load_state().snapshot or {}).get("image")
    if not recorded:
        return Check("snapshot", FAIL, "no snapshot recorded for new clones",
                     f"ccrp {_build_command(provider)} -i INVENTORY (or snapshot create --use from a configured clone)")
    try:
        present = provider.has_image(recorded)
    except CcrpError as exc:
        return _failed("snapshot", exc)
    if present:
        return Check("snapshot", OK, recorded)
    return Check("snapshot", FAIL, f"{recorded} is recorded but gone", f"ccrp {_build_command(provider)} -i INVENTORY")


def _gateway(fleet: Fleet, provider: Gateways) -> Check:
    """provider.entry: gateway: the gateway the state records is the one in the cloud, at the same
    address, and running (the robots' bundles dial that address)."""
    recorded = fleet.store.load_state().gateway
    try:
        found = provider.gateway()
    except CcrpError as exc:
        return _failed("entry gateway", exc)
    if recorded is None:
        return Check("entry gateway", OK if found is None else WARN, "none yet: `fleet up` makes it" if found is None
                     else f"{found.provider_id} exists but the state records none", "" if found is None else "ccrp fleet up")
    if found is None:
        return Check("entry gateway", FAIL, f"{recorded.provider_id} ({recorded.public_ip}) is gone: robots cannot reach their clones",
                     "ccrp fleet up (it makes the gateway again with the same address)")
    if found.public_ip != str(recorded.public_ip) or found.state is not CloneState.RUNNING:
        return Check("entry gateway", FAIL, f"{found.provider_id} is {found.status} at {found.public_ip or 'no address'} "
                     f"(robots dial {recorded.public_ip})", "ccrp fleet up")
    return Check("entry gateway", OK, f"{found.provider_id} at {found.public_ip}")


def _snapshot_images(provider: HostImages) -> Check:
    """Ability.HOST_IMAGES: the disk the backend's snapshot images take on this host, this state's
    and orphans' (Docker's, found by their state labels)."""
    found = provider.images_finding()
    return Check(found.check, found.status, found.detail, found.hint)


def _build_command(provider: Provider) -> str:
    from ..providers.base import Ability

    return "snapshot build" if Ability.LOCAL_BUILD in provider.abilities else "snapshot bake"


def as_dicts(checks: list[Check]) -> list[dict[str, Any]]:
    return [asdict(c) for c in checks]
