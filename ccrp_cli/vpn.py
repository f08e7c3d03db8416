"""Fleet PKI operations behind `ccrp vpn ...`: each takes the fleet lock and returns records."""

from __future__ import annotations

from typing import Any, Callable

from .errors import CcrpError

from .fleet import Fleet
from .pki.store import CRL_WARN_DAYS


def init(fleet: Fleet) -> dict[str, Any]:
    vpn = fleet.inventory.vpn
    with fleet.store.lock():
        created = fleet.pki.init(vpn.key_type, vpn.crl_days)
        fleet.load_allocated()
    pki = fleet.pki
    return {"fleet": fleet.name, "created": created, "ca": str(pki.ca_path), "crl": str(pki.crl_path)}


def issue(fleet: Fleet, robot: str, renew: bool = False) -> list[dict[str, Any]]:
    with fleet.store.lock():
        state = fleet.load_allocated()
        fleet.robot(state, robot)  # unknown robot: input error before anything is written
        results = fleet.pki.issue_robot(robot, fleet.inventory.vpn.cert_days, renew=renew)
    return [_record(fleet, rec) | {"issued": new} for rec, new in results]


def revoke(fleet: Fleet, robot: str, progress: Callable[[str], None] = lambda m: None) -> list[dict[str, Any]]:
    """Revoke the robot's certificates, push the new CRL to every live clone, end its session."""
    with fleet.store.lock():
        state = fleet.store.load_state()
        fleet.robot(state, robot)
        revoked = fleet.pki.revoke_robot(robot, fleet.inventory.vpn.crl_days)
        live = [name for name, rec in state.robots.items() if rec.phase == "ready"]
        if live:
            _push_crl(fleet, live, robot, progress)
    return [_record(fleet, rec) for rec in revoked]


def _push_crl(fleet: Fleet, clones: list[str], robot: str, progress: Callable[[str], None]) -> None:
    from .clones import kill_session
    from .providers import get_provider
    from .render.bundles import BundleFile
    from .render.view import SECRETS_DIR

    provider = get_provider(fleet.inventory)
    crl = BundleFile("crl.pem", fleet.pki.crl_path.read_text(), 0o644, f"{SECRETS_DIR}/crl.pem")
    failed = []
    for name in clones:
        try:
            provider.push_files(name, [crl])  # OpenVPN re-reads crl-verify files when they change
        except CcrpError as exc:
            failed.append(f"{name}: {exc.message}")
    if robot in clones:
        try:
            kill_session(provider, robot)
            progress(f"ended the live VPN session of robot {robot!r}")
        except CcrpError as exc:
            failed.append(f"{robot}: {exc.message}")
    if failed:
        raise CcrpError(
            f"revoked, but the new CRL did not reach every clone ({'; '.join(failed)})",
            hint="run `ccrp fleet up -i INVENTORY` to push it again",
        )
    progress(f"pushed the new CRL to {len(clones)} clone(s)")


def list_certs(fleet: Fleet) -> list[dict[str, Any]]:
    index = fleet.pki.load_index()
    return [_record(fleet, rec) for rec in index.certs]


def crl_warning(fleet: Fleet) -> str | None:
    days = fleet.pki.crl_days_left()
    if days < CRL_WARN_DAYS:
        return (
            f"the CRL of fleet {fleet.name!r} expires in {days:.0f} days: every robot will be refused "
            "after that (re-issue it with `ccrp vpn init`)"
        )
    return None


def _record(fleet: Fleet, rec: Any) -> dict[str, Any]:
    return {
        "serial": rec.serial,
        "cn": rec.cn,
        "profile": rec.profile,
        "robot": rec.robot,
        "not_after": rec.not_after.isoformat(),
        "revoked": rec.revoked,
        "revoked_at": rec.revoked_at.isoformat() if rec.revoked_at else None,
        "path": str(fleet.pki.root / rec.cert_path),
    }
