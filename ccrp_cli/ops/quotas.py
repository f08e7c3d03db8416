"""Quotas before growth: `fleet up`, `clone create` and `fleet scale` hold the clones they will
create against the cloud's quotas first, and refuse in one line naming the quota and the numbers
when one is short, having created nothing (docs/clouds.md "Quotas before growth").

The provider reports the quotas (Provider.quotas: typed records, the cloud's own limit and usage
and what one clone takes); which clones a command creates, and the verdict, are decided here. A
cloud that fails one clone after another at its regional limit leaves a half-grown fleet and an
error per robot; this says so once, before the first create.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..errors import CcrpError
from ..providers.base import Quota
from ..providers.registry import info

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..providers.base import Housekeeping, Lifecycle, Provider

class QuotaError(CcrpError):
    """A command would take more of a quota than is free: refused before anything was created."""


@dataclass(frozen=True)
class Use:
    """One quota and what the clones a command creates take of it."""

    quota: Quota
    need: float

    @property
    def short(self) -> bool:
        return self.need > self.quota.free + 1e-9

    @property
    def after(self) -> float:
        """What would be free once the clones exist (negative: short by that much)."""
        return self.quota.limit - self.quota.used - self.need

    def line(self, kind: str) -> str:
        q = self.quota
        return f"{kind} quota {q.name} in {q.scope}: {q.free:g} free, this needs {self.need:g}"


def new_clones(fleet: Fleet, provider: Lifecycle, robots: Sequence[str]) -> list[str]:
    """Those of `robots` whose clone `fleet up` would create: none in the cloud, not revoked (a
    revoked robot gets no clone, reconcile.plan)."""
    if not robots:
        return []
    actual = provider.query()
    index = fleet.pki.load_index() if fleet.pki.exists() else None
    return [r for r in robots if r not in actual and not (index and fleet.pki.revoked_since(r, index))]


def uses(provider: Housekeeping, creating: Sequence[str]) -> list[Use]:
    """Every quota the provider reports, with what creating `creating` takes of it ([] where the
    backend has none: Docker). Raises CcrpError when the cloud does not tell."""
    return [Use(q, q.need(creating)) for q in provider.quotas(list(creating))]


def fitting(found: list[Use], creating: Sequence[str]) -> int:
    """How many of `creating`, in order, fit every quota."""
    for n in range(len(creating)):
        if any(u.quota.need(creating[: n + 1]) > u.quota.free + 1e-9 for u in found):
            return n
    return len(creating)


def refusal(kind: str, found: list[Use], creating: Sequence[str]) -> QuotaError | None:
    """The one-line refusal when a quota is short, else None."""
    short = [u for u in found if u.short]
    if not short:
        return None
    fit = fitting(found, creating)
    where = "; ".join(dict.fromkeys(u.quota.hint for u in short if u.quota.hint)) or info(kind).quota_hint
    return QuotaError("; ".join(u.line(kind) for u in short),
                      hint=f"{where}; or create at most {fit} of the {len(creating)} new clones for now. "
                           "Nothing was created")


def check(provider: Provider, creating: Sequence[str], progress: Callable[[str], None]) -> list[Use]:
    """Before any create: QuotaError when `creating` needs more of a quota than is free. A cloud
    that does not tell its quotas (no read permission) is said so and not held against."""
    if not creating:
        return []
    try:
        found = uses(provider, creating)
    except CcrpError as exc:
        progress(f"cannot read the {provider.kind} quotas ({exc.one_line()}); creating without checking them")
        return []
    refused = refusal(provider.kind, found, creating)
    if refused is not None:
        raise refused
    return found


def check_growth(fleet: Fleet, provider: Provider, robots: Sequence[str], progress: Callable[[str], None]) -> list[Use]:
    """check() for the clones `fleet up` would create among `robots`."""
    return check(provider, new_clones(fleet, provider, robots), progress)
