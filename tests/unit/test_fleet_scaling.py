"""Per-robot work must not grow with the fleet (issue 12): counted, not timed. Issuing and
rendering every robot of a fleet computes each address once, parses state.json and index.json
once, and looks a robot's certificates up without walking the whole index."""

from __future__ import annotations

import pytest
import yaml

from ccrp_cli.models import addressing
from ccrp_cli.ops import vpn
from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.models.state import FleetState
from ccrp_cli.pki.store import PkiIndex
from ccrp_cli.render import bundles, cloudinit
from ccrp_cli.services.registry import boots
from tests.conftest import LAB

N = 40


@pytest.fixture
def big(ccrp_home, tmp_path):
    inv = yaml.safe_load(LAB.read_text())
    inv["robots"] = [{"name": f"bot{i}"} for i in range(1, N + 1)]
    inv.pop("template")
    (tmp_path / "fleet.yaml").write_text(yaml.safe_dump(inv))
    fleet = Fleet.open(tmp_path / "fleet.yaml")
    vpn.init(fleet)
    return fleet


def counting(monkeypatch, owner, name: str) -> list:
    calls: list = []
    real = getattr(owner, name)

    def counted(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(owner, name, counted)
    return calls


def test_issue_and_render_every_robot_is_linear(big, monkeypatch):
    addr_calls = counting(monkeypatch, addressing, "addresses")
    monkeypatch.setattr("ccrp_cli.fleet.addresses", addressing.addresses)
    index_parses = counting(monkeypatch, PkiIndex, "model_validate_json")
    state_parses = counting(monkeypatch, FleetState, "model_validate")
    names = [r.name for r in big.inventory.robots]
    for name in names:
        vpn.issue(big, name)
    state = big.store.load_state()
    for name in names:
        view = clone_view(big, state, name)
        creds = big.pki.credentials(name)
        cloudinit.user_data(view, boots())
        bundles.edge_bundle(view, creds, "203.0.113.10")
    # Quadratic was N * N addresses() and N parses of each file.
    assert len(addr_calls) == N
    assert len(index_parses) <= 1 and len(state_parses) <= 1


def test_certificate_lookup_does_not_walk_the_index(big):
    for name in ("bot1", "bot2"):
        vpn.issue(big, name)
    index = big.pki.load_index()

    class Counted(list):
        walks = 0

        def __iter__(self):
            Counted.walks += 1
            return super().__iter__()

    index.certs = Counted(index.certs)
    assert big.pki.current(index, "bot2").cn == "bot2"
    big.pki.credentials("bot1")
    big.pki.revoked_since("bot1", index)
    assert Counted.walks == 0


def test_index_and_state_in_memory_follow_the_files(big):
    """What is kept in memory is the file as it is: another run's write (a new file) is read."""
    vpn.issue(big, "bot1")
    second = Fleet(big.inventory, type(big.store)(big.name, home=big.store.root.parent))
    vpn.issue(second, "bot2")
    vpn.revoke(second, "bot2")
    assert big.pki.current(big.pki.load_index(), "bot2") is None
    assert big.pki.revoked_since("bot2") is not None
    assert big.store.load_state().robots["bot2"].phase == "revoked"
