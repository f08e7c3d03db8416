"""Fleet PKI operations behind `ccrp vpn ...`: each takes the fleet lock and returns records."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

from ..errors import CcrpError

from ..fleet import Fleet
from ..pki.store import CRL_WARN_DAYS

if TYPE_CHECKING:
    from ..providers.base import Lifecycle, Provider


def init(fleet: Fleet) -> dict[str, Any]:
    vpn = fleet.inventory.vpn
    with fleet.store.lock():
        created = fleet.pki.init(vpn.key_type, vpn.crl_days)
        fleet.load_allocated()
    pki = fleet.pki
    return {"fleet": fleet.name, "created": created, "ca": str(pki.ca_path), "crl": str(pki.crl_path)}


def issue(fleet: Fleet, robot: str, renew: bool = False, provider: Provider | None = None,
          progress: Callable[[str], None] = lambda m: None) -> list[dict[str, Any]]:
    """Issue the robot's certificates on purpose: this also lets a revoked robot back in.

    --renew revokes the current certificates and rotates the password and tls-crypt key; with a
    provider, a clone that runs gets the new set at once (OpenVPN restarts, the old session ends)
    and every other clone the new CRL. Without one only the PKI changes."""
    with fleet.store.lock():
        state = fleet.load_allocated()
        fleet.robot(state, robot)  # unknown robot: input error before anything is written
        vpn = fleet.inventory.vpn
        results = fleet.pki.issue_robot(robot, vpn.cert_days, renew=renew, enroll=True, crl_days=vpn.crl_days)
        if renew and provider is not None:
            _renew_on_clones(fleet, provider, robot, progress)
    return [_record(fleet, rec) | {"issued": new} for rec, new in results]


# A robot's own certificate goes with its power device's: whoever holds the robot holds the device
# on its power line too.
CERT_KINDS = {"client": ("client", "power"), "power": ("power",), "server": ("server",), "relay": ("relay",),
              "all": ("client", "power", "server", "relay")}


def revoke(fleet: Fleet, robot: str, cert: str = "client", provider: Provider | None = None,
           progress: Callable[[str], None] = lambda m: None) -> list[dict[str, Any]]:
    """Revoke the robot's certificates (its client certificate by default), then, with a provider,
    at once: end its live session on its clone and give every running clone the new CRL."""
    with fleet.store.lock():
        state = fleet.store.load_state()
        fleet.robot(state, robot)
        kinds = CERT_KINDS[cert]
        revoked = fleet.pki.revoke_robot(robot, fleet.inventory.vpn.crl_days, kinds)
        if "client" in kinds and robot in state.robots:
            state.robots[robot].phase = "revoked"  # left out of sharing and of `fleet up` until re-issued
            fleet.store.save_state(state)
        if provider is None:
            return [_record(fleet, rec) for rec in revoked]
        _push_crl(fleet, provider, robot, kill=sorted({rec.cn for rec in revoked if rec.profile in ("client", "power")}),
                  progress=progress)
        if "client" in kinds:
            from .reconcile import reshare

            reshare(fleet, provider, progress)  # its partners drop the revoked robot's clone
        elif kinds == ("power",):
            from ..robot.power import push_passwd

            push_passwd(fleet, provider, robot, progress)  # the clone forgets the device's name
        else:
            _replace_on_clone(fleet, provider, robot, progress)  # new server/relay certificate now
    return [_record(fleet, rec) for rec in revoked]


def _running(provider: Lifecycle) -> list[str]:
    from ..providers.base import CloneState

    return sorted(name for name, rec in provider.query().items() if rec.state is CloneState.RUNNING)


def _replace_on_clone(fleet: Fleet, provider: Provider, robot: str, progress: Callable[[str], None]) -> None:
    """A running clone of `robot` gets its new certificates and secrets at once (fleet up for that
    robot: OpenVPN and the relay restart, partners get the new relay CN)."""
    from .reconcile import up

    if robot not in _running(provider):
        return
    failed = [r for r in up(fleet, provider, progress, only=[robot]) if r.action == "failed"]
    if failed:
        raise CcrpError(f"the clone of {robot!r} did not take its new credentials: {failed[0].detail}",
                        hint="run `ccrp fleet up -i INVENTORY` to push them again")


def _renew_on_clones(fleet: Fleet, provider: Provider, robot: str, progress: Callable[[str], None]) -> None:
    _replace_on_clone(fleet, provider, robot, progress)
    _push_crl(fleet, provider, robot, kill=[], progress=progress)
    progress(f"install the new robot bundle on {robot}: ccrp robot bundle -i INVENTORY {robot}")


def _push_crl(fleet: Fleet, provider: Lifecycle, robot: str, kill: list[str], progress: Callable[[str], None]) -> None:
    """The new CRL to every running clone, whatever its phase (a failed `fleet up` leaves clones
    that serve), in parallel. The robot's own clone comes first and ends the sessions of the CNs
    in `kill` (the robot, its power device) right after taking the CRL: a reconnection then meets
    the new CRL."""
    from concurrent.futures import ThreadPoolExecutor

    from ..probe import kill_session
    from ..render.bundles import crl_file

    crl = crl_file(fleet.pki.crl_path.read_text())
    running = _running(provider)
    order = sorted(running, key=lambda name: name != robot)

    def one(name: str) -> str | None:
        try:
            provider.transport.push_files(name, [crl], restart=[])  # OpenVPN re-reads crl-verify files when they change
            for cn in kill if name == robot else ():
                kill_session(provider, robot, cn)
                progress(f"ended the live VPN session of {cn!r}")
        except CcrpError as exc:
            return f"{name}: {exc.message}"
        return None

    if not order:
        return
    with ThreadPoolExecutor(max_workers=min(provider.max_parallel, len(order))) as pool:
        failed = [f for f in pool.map(one, order) if f]
    if failed:
        raise CcrpError(
            f"revoked, but the new CRL did not reach every clone ({'; '.join(failed)})",
            hint="run `ccrp fleet up -i INVENTORY` to push it again",
        )
    progress(f"pushed the new CRL to {len(order)} running clone(s)")


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


def ensure_pki(fleet: Fleet, say: Callable[[str], None]) -> None:
    """A new fleet's PKI is made by the first command that needs it, as `ccrp vpn init` would
    (which takes the fleet lock: call this before taking it)."""
    if fleet.pki.exists():
        return
    made = init(fleet)
    say(f"fleet {fleet.name!r} had no PKI yet: created its CA {made['ca']} (as `ccrp vpn init`)")


def vpn_issue(fleet: Fleet, robot: str, renew: bool, say: Callable[[str], None]) -> list[dict[str, Any]]:
    """`ccrp vpn issue-cert`: the robot's client and its clone's server certificates (the PKI
    first if the fleet has none); with `renew`, a running clone takes the new set at once."""
    from ..providers import get_provider

    fleet.robot(fleet.store.load_state(), robot)
    ensure_pki(fleet, say)
    return issue(fleet, robot, renew, get_provider(fleet.inventory) if renew else None, say)


def vpn_revoke(fleet: Fleet, provider: Provider, robot: str, say: Callable[[str], None],
               cert: str = "client") -> list[dict[str, Any]]:
    """`ccrp vpn revoke`: revoke the robot's certificates, end its session, push the CRL."""
    return revoke(fleet, robot, cert, provider, say)
