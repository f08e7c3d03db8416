"""Fleet PKI operations behind `ccrp vpn ...`: each takes the fleet lock and returns records."""

from __future__ import annotations

from typing import Any

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


def revoke(fleet: Fleet, robot: str) -> list[dict[str, Any]]:
    with fleet.store.lock():
        fleet.robot(fleet.store.load_state(), robot)
        revoked = fleet.pki.revoke_robot(robot, fleet.inventory.vpn.crl_days)
    return [_record(fleet, rec) for rec in revoked]


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
