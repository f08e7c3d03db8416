"""Live openstack: a clone from the fleet's snapshot via `ccrp fleet up`, a robot connected over
OpenVPN, `ccrp status --json` showing it, `ccrp fleet down`. Needs OS_CLOUD (an entry of clouds.yaml)
and CCRP_LIVE_INVENTORY; see tests/live/live.py and docs/clouds.md."""

from __future__ import annotations

from tests.live import live

pytestmark = live.marks("openstack")


def test_clone_robot_status_down(tmp_path):
    live.run("openstack", tmp_path)
