"""`clone start` says `started` when the provider started the clone (run_instance's origin), not from
a state read before: a clone that was running is `reused`, one that does not exist is refused."""

from __future__ import annotations

import pytest

from ccrp_cli.ops.clone import clone_start
from ccrp_cli.ops import reconcile
from ccrp_cli.ops.clones import CloneResult
from ccrp_cli.errors import InputError
from ccrp_cli.providers.base import CloneRecord, CloneState, Origin


class Clones:
    """query() as a provider answers it; `fleet up` (reconcile.up) is replaced below."""

    def __init__(self, **states: CloneState) -> None:
        self.states = states

    def query(self) -> dict[str, CloneRecord]:
        return {r: CloneRecord(robot=r, provider_id=r, state=s, status=s.value) for r, s in self.states.items()}


@pytest.mark.parametrize("before, origin, said", [
    (CloneState.STOPPED, Origin.RESUMED, "started"),
    (CloneState.RUNNING, Origin.REUSED, "reused"),
    # Stopped by the time `clone start` asked, started by someone else before its lock: not this run's start.
    (CloneState.STOPPED, Origin.REUSED, "reused"),
    # Still stopping when asked, then stopped and started by this run: the provider's word counts.
    (CloneState.STOPPING, Origin.RESUMED, "started"),
])
def test_clone_start_reports_what_the_provider_did(lab, monkeypatch, before, origin, said):
    ups = []

    def up(fleet, provider, say, only):
        ups.append(only)
        return [CloneResult(only[0], "reused", "198.51.100.7", 1.0, origin)]

    monkeypatch.setattr(reconcile, "up", up)
    items = clone_start(lab, Clones(nao1=before), "nao1", say=lambda line: None)
    assert ups == [["nao1"]] and [(i.robot, i.action) for i in items] == [("nao1", said)]


def test_clone_start_refuses_a_robot_without_a_clone_and_creates_nothing(lab, monkeypatch):
    monkeypatch.setattr(reconcile, "up", lambda *a, **k: pytest.fail("fleet up ran"))
    with pytest.raises(InputError, match="no clone to start"):
        clone_start(lab, Clones(nao2=CloneState.RUNNING), "nao1", say=lambda line: None)


def test_a_record_is_created_only_when_the_provider_made_it():
    rec = CloneRecord(robot="r", provider_id="i", state=CloneState.RUNNING, status="running")
    assert rec.origin is None and not rec.created  # what query() lists
    assert rec.model_copy(update={"origin": Origin.CREATED}).created
    assert not rec.model_copy(update={"origin": Origin.RESUMED}).created
