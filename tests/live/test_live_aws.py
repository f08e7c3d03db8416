"""Live aws: a clone from the fleet's snapshot via `ccrp fleet up`, a robot connected over
OpenVPN, `ccrp status --json` showing it, `ccrp fleet down`. Needs AWS_PROFILE, or AWS_ACCESS_KEY_ID + AWS_SECRET_ACCESS_KEY
and CCRP_LIVE_INVENTORY; see tests/live/live.py and docs/clouds.md."""

from __future__ import annotations

from tests.live import live

pytestmark = live.marks("aws")


def test_clone_robot_status_down(tmp_path):
    live.run("aws", tmp_path)
