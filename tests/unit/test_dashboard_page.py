"""The dashboard page's script (ccrp_cli/dashboard/static/app.js) run in Node on a stand-in DOM with
fake timers and a recording fetch (tests/unit/app_js_harness.js): what it sends when a drive key is
held, when the page loses focus or is hidden, and how it starts the camera. No browser: the real
one is tests/e2e/test_dashboard_browser.py's."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from tests.conftest import ROOT

NODE = shutil.which("node") or shutil.which("nodejs")
pytestmark = pytest.mark.skipif(NODE is None, reason="needs Node.js to run the page's script outside a browser")
HARNESS = Path(__file__).with_name("app_js_harness.js")
APP = ROOT / "ccrp_cli/dashboard/static/app.js"


def run(scenario: str) -> dict:
    proc = subprocess.run([NODE, str(HARNESS), str(APP), scenario], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_a_held_key_is_repeated_and_leaving_the_page_stops_the_robot():
    """A held drive key kept the robot moving when the page lost focus: the keyup went to another
    window. Now the page sends a stop on `blur` and on `visibilitychange` to hidden and forgets the
    key; while a key is held it sends it again every 200 ms, since the robot's deadman stops it
    after 0.5 s without a command."""
    steps = run("drive")
    assert steps["pressed"] == [[0.2, 0]]
    assert len(steps["held 1 s"]) >= 4 and set(map(tuple, steps["held 1 s"])) == {(0.2, 0)}
    assert steps["blur"] == [[0, 0]]  # stopped at once
    assert steps["after blur"] == []  # and the key forgotten: no more forward
    assert steps["hidden"][-1] == [0, 0] and set(map(tuple, steps["hidden"][:-1])) == {(0, -0.5)}
    assert steps["after hidden"] == []
    assert steps["blur at rest"] == []  # nothing moving: nothing sent
    assert steps["pressed and let go"] == [[0.2, 0], [0, 0]]  # a key let go still stops it


def test_the_camera_is_started_by_a_post_with_the_csrf_token_and_read_by_gets():
    """Choosing a robot POSTs the start with the page's CSRF token, then reads frames by GET; an
    agent that ended is started again once; a start refused is not retried by the polls."""
    steps = run("camera")
    start = ["POST", "/api/camera/nao1/start", "csrf-of-this-page"]
    read = ["GET", "/api/camera/nao1", None]
    assert steps["chosen"] == [start, read]
    assert steps["next poll"] == [read]
    assert steps["agent ended"] == [read, start, read]
    assert steps["start refused"] == [read, start, read]  # one start, then reads only
