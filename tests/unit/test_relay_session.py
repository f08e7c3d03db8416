"""The relay agent's session across config changes (agent/relay.py Relay._open, main's loop)."""

from __future__ import annotations

import pytest

pytest.importorskip("zenoh")

from tests.unit.helpers import load_agent  # noqa: E402


class Session:
    def __init__(self, close_fails: bool) -> None:
        self.close_fails, self.closed = close_fails, False

    def close(self) -> None:
        self.closed = True
        if self.close_fails:
            raise RuntimeError("close operation timed out!")  # as Zenoh's ZError read on a clone


class Topic:
    def __init__(self, *args) -> None:
        self.args, self.closed = args, False

    def close(self) -> None:
        self.closed = True


class Ros:
    Export = Topic
    Import = Topic


def config(peers: list[str]) -> dict:
    return {"id": "c" + "1" * 23, "fleet": "lab", "robot": "nao1", "listen": "tls/127.0.0.1:7447",
            "tls": {"ca": "/nonexistent/ca", "cert": "/nonexistent/crt", "key": "/nonexistent/key"},
            "peers": {p: {"endpoint": f"tls/10.0.0.{i + 2}:7447", "cn": f"relay-{p}-1", "id": "c" + str(i) * 23}
                      for i, p in enumerate(peers)},
            "exports": ["/faces"], "imports": [{"as": "/nao2/faces", "source": "nao2", "topic": "/faces"}]}


def test_a_session_whose_close_times_out_is_replaced_and_the_topics_declared_again(monkeypatch, capsys):
    """A deleted clone's link made Zenoh's close time out: the relay must still open the session
    for its new peers and declare its exports and imports on it."""
    agent = load_agent()
    opened: list[Session] = []

    def open_session(_config):
        opened.append(Session(close_fails=not opened))  # the first one's close fails
        return opened[-1]

    monkeypatch.setattr(agent.zenoh, "open", open_session)
    relay = agent.Relay(config(["nao2", "robot1"]), Ros())
    first_export = relay.exports["/faces"]
    relay.apply(config(["nao2"]))  # robot1 deleted: its link is gone
    assert len(opened) == 2 and opened[0].closed and relay.session is opened[1]
    assert first_export.closed and not relay.exports["/faces"].closed and "/nao2/faces" in relay.imports
    assert "closing the previous session: RuntimeError: close operation timed out!" in capsys.readouterr().err


def test_each_session_has_its_own_zenoh_id_and_peers_are_named_by_the_stable_part():
    from types import SimpleNamespace

    agent = load_agent()
    stable = "c" + "a" * 23
    ids = {agent.session_id(stable) for _ in range(20)}
    assert len(ids) == 20 and all(len(i) == 32 and i.startswith(stable) for i in ids)
    session = SimpleNamespace(info=SimpleNamespace(peers_zid=lambda: ["c" + "1" * 23 + "0badf00d"]))
    peers = config(["nao2", "robot1"])["peers"]  # ids "c0…" and "c1…"
    assert agent.connected_peers(session, peers) == {"nao2": False, "robot1": True}
    assert agent.connected_peers(None, peers) == {"nao2": False, "robot1": False}
