"""Clones leave after their partners let go of them (reconcile.retire and drain)."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

from ccrp_cli.ops import reconcile
from ccrp_cli.ops.clones import CloneResult
from ccrp_cli.errors import CcrpError


class Partners:
    """exec() answers `cat <report>` as a clone would; `letgo` calls before a partner drops."""

    max_parallel = 4

    def __init__(self, peers: dict[str, list[str]], letgo: int = 1, stale: bool = False) -> None:
        self.peers, self.letgo, self.stale, self.calls, self.log = peers, letgo, stale, {}, []

    transport = property(lambda self: self)  # a fake clone is its own transport
    def exec(self, robot: str, argv: list[str], timeout: float = 60) -> tuple[int, str]:
        if robot == "gone":
            raise CcrpError("gone: not answering")
        if "relay" not in argv[1]:
            return 1, "cat: No such file or directory"
        n = self.calls[robot] = self.calls.get(robot, 0) + 1
        peers = [p for p in self.peers[robot] if n <= self.letgo or p != "robot1"]
        self.log.append(("report", robot, peers))
        return 0, json.dumps({"time": time.time() - (60 if self.stale else 0), "peers": dict.fromkeys(peers, True)})


def test_drain_waits_until_every_partner_dropped_the_leaving_clone():
    provider = Partners({"nao1": ["nao2", "robot1"], "nao2": ["robot1"]}, letgo=2)
    reconcile.drain(provider, ["nao1", "nao2"], {"robot1"}, print)
    assert provider.calls == {"nao1": 3, "nao2": 3}


def test_drain_does_not_wait_for_an_agent_that_is_not_running_or_a_clone_that_does_not_answer(capsys):
    provider = Partners({"nao1": ["robot1"]}, letgo=99, stale=True)
    t0 = time.monotonic()
    reconcile.drain(provider, ["nao1"], {"robot1"}, print)
    notes: list[str] = []
    reconcile.drain(provider, ["gone"], {"robot1"}, notes.append)
    assert time.monotonic() - t0 < 2 and provider.calls == {"nao1": 1}
    assert notes == ["not waiting for partners to let go: gone: not answering"]


def test_drain_gives_up_after_its_timeout_and_says_so(monkeypatch):
    monkeypatch.setattr(reconcile, "DRAIN_TIMEOUT", 1.0)
    notes: list[str] = []
    reconcile.drain(Partners({"nao1": ["robot1"]}, letgo=99), ["nao1"], {"robot1"}, notes.append)
    assert len(notes) == 1 and notes[0].startswith("nao1 still linked to robot1 after 1 s")


def test_retire_reshares_and_drains_before_it_deletes(monkeypatch):
    order: list[tuple] = []
    state = SimpleNamespace(robots={"robot1": SimpleNamespace(phase="ready")})
    writer = SimpleNamespace(state=state, update=lambda r, **kw: order.append(("update", r, kw["phase"])))
    monkeypatch.setattr(reconcile, "reshare", lambda fleet, provider, progress: order.append(("reshare",)) or ["nao1"])
    monkeypatch.setattr(reconcile, "drain", lambda provider, partners, leaving, progress:
                        order.append(("drain", tuple(partners), tuple(leaving))))
    monkeypatch.setattr(reconcile, "delete_clone", lambda fleet, provider, w, r, forget:
                        order.append(("delete", r, forget)) or CloneResult(r, "deleted"))
    results = reconcile.retire(None, Partners({}), writer, ["robot1"], print, forget=True)
    assert [r.action for r in results] == ["deleted"]
    assert order == [("update", "robot1", "deleting"), ("reshare",), ("drain", ("nao1",), ("robot1",)),
                     ("delete", "robot1", True)]
    assert reconcile.retire(None, Partners({}), writer, [], print, forget=True) == []
