"""`ccrp doctor`: is this machine and account ready to run the fleet? One row per check, each
with what to do when it fails. Read-only: nothing is created."""

from __future__ import annotations

import importlib.util
import shutil
from dataclasses import asdict, dataclass

from .errors import CcrpError
from .fleet import Fleet

OK, FAIL, WARN, SKIP = "ok", "fail", "warn", "skip"
# Import name -> pip extra, per provider kind. paramiko: the SSH transport of every cloud.
SDKS = {
    "docker": [("docker", "docker")],
    "aws": [("boto3", "aws"), ("paramiko", "aws")],
    "openstack": [("openstack", "openstack"), ("paramiko", "openstack")],
    "gcp": [("google.cloud.compute_v1", "gcp"), ("paramiko", "gcp")],
}
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
    missing = [(m, extra) for m, extra in SDKS[kind] if not _installed(m)]
    for module, extra in SDKS[kind]:
        if (module, extra) in missing:
            checks.append(Check(f"sdk {module}", FAIL, "not installed", f"pip install 'ccrp[{extra}]'"))
        else:
            checks.append(Check(f"sdk {module}", OK, "installed"))
    provider = None
    if not missing:
        provider, check = _provider(fleet)
        checks.append(check)
    if provider is not None:
        checks += _credentials(provider) + _quotas(provider) + [_snapshot(fleet, provider)]
    if kind == "docker" and shutil.which("mmdebstrap") is None:
        checks.append(Check("tool mmdebstrap", WARN, "not found",
                            "apt-get install mmdebstrap (builds the base image when it is missing)"))
    for tool, why in OPTIONAL_TOOLS.items():
        found = shutil.which(tool)
        checks.append(Check(f"tool {tool}", OK if found else WARN, found or f"not found (optional: {why})",
                            "" if found else f"install {tool} (optional)"))
    return checks


def _provider(fleet: Fleet):
    from .providers import get_provider

    kind = fleet.inventory.provider.kind
    name = "docker engine" if kind == "docker" else f"{kind} client"
    try:
        provider = get_provider(fleet.inventory)
    except CcrpError as exc:
        return None, _failed(name, exc)
    if kind == "docker":
        version = provider.client.version()
        return provider, Check(name, OK, f"Docker {version.get('Version', '?')} (API {version.get('ApiVersion', '?')})")
    return provider, Check(name, OK, f"region/cloud {getattr(fleet.inventory.provider, 'region', '') or getattr(fleet.inventory.provider, 'cloud', '')}".strip())


def _credentials(provider) -> list[Check]:
    probe = getattr(provider, "check_credentials", None)
    if provider.kind == "docker":
        return []  # the engine answering is the credential
    if probe is None:
        return [Check("credentials", SKIP, f"the {provider.kind} provider cannot check credentials")]
    try:
        return [Check("credentials", OK, probe())]
    except CcrpError as exc:
        return [_failed("credentials", exc)]


def _quotas(provider) -> list[Check]:
    probe = getattr(provider, "quotas", None)
    if probe is None:
        return []
    try:
        quotas = probe()
    except CcrpError as exc:
        return [Check("quotas", WARN, exc.message, exc.hint or "grant read access to quotas to see them")]
    return [
        Check(f"quota {name}", OK if need <= limit else FAIL, f"limit {limit:g}, fleet needs {need}",
              "" if need <= limit else "raise the quota (AWS: Service Quotas console) or shrink the fleet")
        for name, limit, need in quotas
    ]


def _snapshot(fleet: Fleet, provider) -> Check:
    recorded = (fleet.store.load_state().snapshot or {}).get("image")
    if not recorded:
        return Check("snapshot", FAIL, "no snapshot recorded for new clones",
                     "ccrp snapshot build -i INVENTORY (or snapshot create --use from a configured clone)")
    try:
        has = getattr(provider, "has_image", None)
        present = has(recorded) if has else any(recorded in (s.id, s.name) for s in provider.list_snapshots())
    except CcrpError as exc:
        return _failed("snapshot", exc)
    if present:
        return Check("snapshot", OK, recorded)
    return Check("snapshot", FAIL, f"{recorded} is recorded but gone", "ccrp snapshot build -i INVENTORY")


def as_dicts(checks: list[Check]) -> list[dict]:
    return [asdict(c) for c in checks]
