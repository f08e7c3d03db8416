"""Fixtures of the unit tests beyond tests/conftest.py's."""

from __future__ import annotations

import pytest

from ccrp_cli.fleet import Fleet
from tests.conftest import LAB


@pytest.fixture
def lab_up(ccrp_home):
    """The lab fleet with every clone recorded as ready."""
    from ccrp_cli import vpn

    fleet = Fleet.open(LAB)
    vpn.init(fleet)
    state = fleet.load_allocated()
    plan = fleet.plan(state)
    for name, rec in state.robots.items():
        rec.phase = "ready"
        fleet.pki.issue_relay(name, str(plan[name].common_ip), 30)  # as ensure_clone does
    fleet.store.save_state(state)
    return fleet, state
