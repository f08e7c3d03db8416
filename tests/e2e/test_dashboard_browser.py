"""`ccrp dashboard` in a real browser on a real Docker fleet: Debian's chromium, headless, driven by
selenium through Debian's chromedriver.

A fleet of its own (nao1 and nao2 from inventories/lab.yaml, own subnets and CCRP_HOME) is brought
up by the CLI; `ccrp dashboard --bind 127.0.0.1:0` runs as a user starts it, and the test reads the
URL it prints. Then: a request without the token is refused; the page opened with the token lists
the fleet; a simulated robot connects (`ccrp robot sim --robot nao1`) and the page shows it without
reloading; a teleop key press on the page (the arrow up, after nao1's Drive button) reaches the
simulated robot, which logs it, and the page shows its latency; `ccrp robot teleop` does the same
from the CLI; nao1's Camera button shows its camera's latest frame as its clone sees it (a 320x240
JPEG, refreshed), as `ccrp robot camera` writes it; its Power off button switches the simulated robot off (its VPN, watchdog and node
stopped, its power device still reporting) and `ccrp robot power on` brings it back; the Revoke button (a POST with the session's CSRF token, from the browser) revokes nao2
and the page reports the action's progress and the robot's new state; nao1's clone stopped behind
the dashboard's back is an alert, its robot's watchdog goes brainless within the default 6 s
(page, `ccrp status`), and its Start button brings it and its robot back; Scale adds a
template robot's clone. Screenshots are taken (nao1 connected; after the revoke), and replace
docs/img/dashboard.png and dashboard-revoke.png with CCRP_UPDATE_SCREENSHOTS=1. Browser,
dashboard, robot and fleet are removed even when a step fails.
"""

from __future__ import annotations

import datetime as dt
import os
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from tests.conftest import ROOT
from tests.e2e.browser import MISSING, cell, chromium, motor_log, press, received_commands, running_dashboard, wait
from tests.e2e.fleet import NO_DOCKER, start_fleet, wait_for

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(NO_DOCKER is not None, reason=f"needs a running Docker engine ({NO_DOCKER})"),
    pytest.mark.skipif(MISSING is not None, reason=str(MISSING)),
]
if MISSING is None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import WebDriverWait

# The screenshots in the docs are replaced when asked (as golden files are), else written to tmp.
SHOTS = ROOT / "docs" / "img" if os.environ.get("CCRP_UPDATE_SCREENSHOTS") else None
ROBOTS = ("nao1", "nao2")


def two_robots(data: dict) -> None:
    data["robots"] = [r for r in data["robots"] if r["name"] in ROBOTS]


@pytest.fixture(scope="module")
def fleet(request, tmp_path_factory):
    f = start_fleet(request, tmp_path_factory, "dsh", edit=two_robots)
    f.inv("fleet", "up", check=True)
    return f


@pytest.fixture(scope="module")
def dashboard(fleet):
    with running_dashboard(fleet) as d:
        yield d


@pytest.fixture(scope="module")
def browser(dashboard, tmp_path_factory):
    with chromium(tmp_path_factory.mktemp("chromium")) as driver:
        yield driver


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    return SHOTS or tmp_path_factory.mktemp("screenshots")


def test_a_request_without_the_token_is_refused(dashboard):
    for path in ("/", "/events", "/api/status", "/static/app.js"):
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(dashboard["base"].rstrip("/") + path, timeout=10)
        assert refused.value.code == 401, path
        assert dashboard["token"] not in refused.value.read().decode()
    request = urllib.request.Request(dashboard["base"] + "api/actions/fleet-scale", data=b'{"size": 0}',
                                     headers={"Content-Type": "application/json"}, method="POST")
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=10)
    assert refused.value.code == 401


def test_page_lists_the_fleet_and_updates_when_a_robot_connects(fleet, dashboard, browser, shots):
    t0 = time.monotonic()
    browser.get(dashboard["base"])  # without the token: the refusal, and no fleet
    assert "needs its access token" in browser.find_element(By.TAG_NAME, "body").text
    assert not browser.find_elements(By.CSS_SELECTOR, "tr[data-robot]") and not browser.get_cookies()
    browser.get(dashboard["url"])
    wait(browser, "the page lists both robots", lambda d: all(cell(d, r, "state").startswith("running") for r in ROBOTS), 30)
    assert "token=" not in browser.current_url  # the token left the address bar (redirect to /)
    assert dashboard["token"] not in browser.page_source
    cookie = next(c for c in browser.get_cookies() if c["name"].startswith("ccrp_dashboard_"))
    assert cookie["httpOnly"] and cookie["sameSite"] == "Strict" and cookie["value"] != dashboard["token"]
    assert cell(browser, "nao1", "vpn") == "no"
    wait(browser, "the disconnected robot is an alert",
         lambda d: d.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="robot-disconnected"][data-robot="nao1"]'), 10)
    browser.execute_script("window.ccrpSamePage = 42")  # gone if the page reloads

    fleet.inv("robot", "sim", "--robot", "nao1", check=True)
    wait(browser, "nao1 shown connected with its node",
         lambda d: cell(d, "nao1", "vpn").startswith("connected") and "/nao1_demo" in cell(d, "nao1", "nodes"), 30)
    assert browser.execute_script("return window.ccrpSamePage") == 42
    assert not browser.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="robot-disconnected"][data-robot="nao1"]')
    fleet.log.append(f"page lists the fleet, robot connected and shown: {time.monotonic() - t0:.1f}s")
    assert browser.save_screenshot(str(shots / "dashboard.png"))


def test_a_teleop_key_press_reaches_the_simulated_robot(fleet, dashboard, browser, shots):
    t0 = time.monotonic()
    press(browser, "nao1", "button:not(.danger)", "Drive")
    assert browser.find_element(By.ID, "teleop-robot").get_attribute("value") == "nao1"
    assert received_commands(fleet, "nao1") == []
    pressed = time.time()
    browser.find_element(By.TAG_NAME, "body").send_keys(Keys.ARROW_UP)  # down and up: forward, then stop
    wait(browser, "the robot's acknowledgement of the key shown with its latency",
         lambda d: d.find_element(By.ID, "teleop-last").get_attribute("class") == "ok"
         and d.find_element(By.ID, "teleop-last").get_attribute("data-round-trip-ms"), 30)
    wait(browser, "the stop sent when the key was let go", lambda d: any(
        c["linear"] == 0 for c in received_commands(fleet, "nao1")), 30)
    got = received_commands(fleet, "nao1")
    forward = [c for c in got if c["linear"] == 0.2 and c["angular"] == 0]
    assert forward and forward[0]["t"] >= pressed and forward[0]["motors"] == "enabled", got
    assert got[-1]["linear"] == 0 and got[-1]["angular"] == 0, got  # letting go stopped it last
    last = browser.find_element(By.ID, "teleop-last")
    shown_ms = float(last.get_attribute("data-round-trip-ms"))
    assert 0 < shown_ms < 5000 and "reached the robot in" in last.text, last.text
    fleet.log.append(f"teleop key press -> robot: {time.monotonic() - t0:.1f}s (round trip shown {shown_ms} ms, "
                     f"one way {last.get_attribute('data-one-way-ms')} ms, request {last.get_attribute('data-request-ms')} "
                     f"ms via {last.get_attribute('data-via')})")
    # The next keys go through the operator node the first one left on the clone: no node to start.
    n = len(got)
    browser.find_element(By.ID, "teleop-right").click()
    _, journal = fleet.container("clone", "nao1").exec_run(["journalctl", "-u", "ccrp-teleop", "--no-pager", "-n", "20"])
    fleet.log.append("ccrp-teleop on nao1's clone:\n" + journal.decode(errors="replace"))
    wait(browser, "a turn through the operator node kept on the clone",
         lambda d: d.find_element(By.ID, "teleop-last").get_attribute("data-via") == "operator"
         and float(d.find_element(By.ID, "teleop-last").get_attribute("data-angular") or 0) == -0.5, 30)
    turned = received_commands(fleet, "nao1")[n:]
    assert turned and all((c["linear"], c["angular"]) == (0, -0.5) for c in turned), turned
    fast = float(browser.find_element(By.ID, "teleop-last").get_attribute("data-request-ms"))
    fleet.log.append(f"teleop button through the operator: request {fast} ms")
    assert browser.save_screenshot(str(shots / "dashboard-teleop.png"))
    # The CLI form: one command, its latency in JSON.
    import json

    out = json.loads(fleet.inv("robot", "teleop", "--robot", "nao1", "--linear", "-0.1", "--angular", "0.3", "--json",
                               check=True).stdout)
    assert out["acknowledged"] and out["round_trip_ms"] > 0 and out["one_way_ms"] is not None, out
    assert any(c["linear"] == -0.1 and c["angular"] == 0.3 for c in received_commands(fleet, "nao1"))
    fleet.log.append(f"ccrp robot teleop: one way {out['one_way_ms']} ms, round trip {out['round_trip_ms']} ms, "
                     f"request {out['request_ms']} ms")
    # nao2 has no robot: refused in one line, exit not 0.
    refused = fleet.inv("robot", "teleop", "--robot", "nao2", "--linear", "0.1", "--timeout", "2")
    assert refused.returncode != 0 and "nothing subscribes" in refused.stderr and "Traceback" not in refused.stderr


def test_a_held_key_is_repeated_and_stops_when_the_page_loses_focus_or_is_hidden(fleet, dashboard, browser):
    """A drive key held down (no keyboard repeat under WebDriver: one keydown) is sent again every
    200 ms; the page losing focus (`blur`) or being hidden (`visibilitychange`) stops the robot at
    once although no keyup came, and forgets the key. The robot's own deadman stops a single
    command after 0.5 s (its `deadman` line in the motion log)."""
    from selenium.webdriver.common.action_chains import ActionChains

    assert browser.find_element(By.ID, "teleop-robot").get_attribute("value") == "nao1"  # chosen by the test above
    ops = [("blur", "window.dispatchEvent(new Event('blur'))"),
           ("hidden", ("Object.defineProperty(document, 'hidden', {configurable: true, get: () => true});"
                       "document.dispatchEvent(new Event('visibilitychange'));"))]
    for what, leave in ops:
        n, pressed = len(received_commands(fleet, "nao1")), time.time()
        ActionChains(browser).key_down(Keys.ARROW_UP).perform()
        wait(browser, f"the held key sent again ({what})", lambda d, n=n, pressed=pressed: len(
            [c for c in received_commands(fleet, "nao1")[n:] if c["linear"] == 0.2 and c["t"] >= pressed]) >= 4, 30)
        browser.execute_script(leave)
        left = time.time()
        wait(browser, f"the stop sent when the page was left ({what})", lambda d, n=n: any(
            c["linear"] == 0 and c["angular"] == 0 for c in received_commands(fleet, "nao1")[n:]), 30)
        time.sleep(1.5)  # a forward still under way may land; none after the stop
        got = received_commands(fleet, "nao1")[n:]
        stop = max(i for i, c in enumerate(got) if (c["linear"], c["angular"]) == (0, 0))
        assert all((c["linear"], c["angular"]) == (0, 0) for c in got[stop:]), got
        assert got[stop]["t"] - left < 5, got
        browser.execute_script("delete document.hidden")
        ActionChains(browser).key_up(Keys.ARROW_UP).perform()  # the key's keyup, late: nothing moves, nothing sent
    # One command from the pad, no stop from the page: the robot's deadman stops it.
    n = len(motor_log(fleet, "nao1"))
    browser.find_element(By.ID, "teleop-left").click()
    wait(browser, "the robot's deadman stop after the pad's single command", lambda d: any(
        c.get("deadman") for c in motor_log(fleet, "nao1")[n:]), 30)
    log = motor_log(fleet, "nao1")[n:]
    stop = next(c for c in log if c.get("deadman"))
    turn = [c for c in log if (c["linear"], c["angular"]) == (0, 0.5) and c["t"] <= stop["t"]][-1]  # (the last resend)
    assert (stop["linear"], stop["angular"]) == (0, 0) and 0.5 <= stop["t"] - turn["t"] < 2.0, log
    fleet.log.append(f"robot deadman: stopped {stop['t'] - turn['t']:.2f} s after the last command")


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's frame header, walking its segments from the start."""
    assert data[:2] == b"\xff\xd8" and data.rstrip(b"\0")[-2:] == b"\xff\xd9", data[:16]
    i = 2
    while i + 9 < len(data):
        assert data[i] == 0xFF, f"no JPEG marker at {i}"
        marker, length = data[i + 1], int.from_bytes(data[i + 2:i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # SOFn: precision, height, width
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        i += 2 + length
    raise AssertionError("no frame header in the JPEG")


def page_fetch(browser, path: str) -> dict:
    """GET `path` with the page's session: status, headers, body (base64)."""
    return browser.execute_async_script("""
        const done = arguments[arguments.length - 1];
        fetch(arguments[0], {credentials: "same-origin"}).then(async (r) => {
          const bytes = new Uint8Array(await r.arrayBuffer());
          let bin = ""; for (const b of bytes) bin += String.fromCharCode(b);
          done({status: r.status, type: r.headers.get("content-type"), cache: r.headers.get("cache-control"),
                body: btoa(bin)});
        }).catch((e) => done({status: 0, error: String(e)}));""", path)


def page_post(browser, path: str) -> dict:
    """POST `path` as the page does (its session, its CSRF token): status and JSON body."""
    return browser.execute_async_script("""
        const done = arguments[arguments.length - 1];
        const csrf = document.querySelector('meta[name="ccrp-csrf"]').content;
        fetch(arguments[0], {method: "POST", credentials: "same-origin", headers: {"X-CCRP-CSRF": csrf}})
          .then(async (r) => done({status: r.status, body: await r.json()}))
          .catch((e) => done({status: 0, error: String(e)}));""", path)


def test_the_camera_view_shows_the_latest_frame_from_the_clone(fleet, dashboard, browser, shots):
    import base64
    import json

    t0 = time.monotonic()
    press(browser, "nao1", "button.camera", "Camera")
    shown = "const i = document.getElementById('camera-img'); " \
            "return i.dataset.robot === 'nao1' && i.complete && i.naturalWidth ? [i.naturalWidth, i.naturalHeight] : null;"
    size = wait(browser, "a camera frame of nao1 decoded by the browser", lambda d: d.execute_script(shown), 30)
    assert size == [320, 240]  # the simulated robot's camera, as its clone received it
    fleet.log.append(f"Camera clicked -> first frame shown: {time.monotonic() - t0:.1f}s")
    img = browser.find_element(By.ID, "camera-img")
    src = img.get_attribute("src")
    assert src.startswith("data:image/jpeg;base64,")
    data = base64.b64decode(src.split(",", 1)[1])
    assert jpeg_size(data) == (320, 240)
    first = int(img.get_attribute("data-seq"))
    try:  # the decoded colours, where Pillow is at hand: the demo node's rgb8 frame is one colour
        from PIL import Image
    except ImportError:
        Image = None
    if Image is not None:
        import io

        picture = Image.open(io.BytesIO(data))
        picture.load()
        # The demo node's frame is one colour (s, 255 - s, 128) in rgb8. JPEG moves a saturated colour
        # by some 15 levels; red and blue swapped (the frame encoded as bgr8) would put s in blue.
        r, g, b = picture.convert("RGB").getpixel((160, 120))
        assert abs(r + g - 255) <= 24 and abs(b - 128) <= 24, (r, g, b)
    # Refreshed while shown: a later frame within a poll or two, its age on the page.
    wait(browser, "a newer frame shown", lambda d: int(d.find_element(By.ID, "camera-img").get_attribute("data-seq") or 0) > first, 20)
    info = browser.find_element(By.ID, "camera-info")
    assert info.get_attribute("class") == "ok" and "s old" in info.text and "320x240 rgb8" in info.text, info.text
    assert 0 <= float(info.get_attribute("data-age-s")) < 10, info.text
    read_ms = img.get_attribute("data-read-ms")
    fleet.log.append(f"camera view: frame read on the clone in {read_ms} ms, {img.get_attribute('data-age-ms')} ms old there")
    assert browser.save_screenshot(str(shots / "dashboard-camera.png"))
    # The endpoint itself, with the page's session: a JPEG never cached; nao2 (no robot) a 503 that says why.
    got = page_fetch(browser, "/api/camera/nao1")
    assert (got["status"], got["type"], got["cache"]) == (200, "image/jpeg", "no-store"), got.get("error")
    assert jpeg_size(base64.b64decode(got["body"])) == (320, 240)
    # nao2's camera was never started: a GET says so and starts nothing on its clone; the page's POST
    # (the Camera button's) starts the agent, which then says why there is no frame.
    got = page_fetch(browser, "/api/camera/nao2")
    assert got["status"] == 503 and '"why":"no-agent"' in base64.b64decode(got["body"]).decode()
    rc, _ = fleet.container("clone", "nao2").exec_run(["systemctl", "is-active", "--quiet", "ccrp-camera"])
    assert rc != 0  # no camera unit on nao2's clone
    # ...but its agent, which `fleet up` pushed (the camera service): the start below only starts it.
    from ccrp_cli.services.camera import AGENT, agent_file

    rc, held = fleet.container("clone", "nao2").exec_run(["cat", AGENT])
    assert rc == 0 and held.decode() == agent_file().content
    started = page_post(browser, "/api/camera/nao2/start")
    assert started == {"status": 200, "body": {"robot": "nao2", "agent": "started"}}, started
    got = page_fetch(browser, "/api/camera/nao2")
    assert got["status"] == 503 and "nothing publishes /camera/image_raw" in base64.b64decode(got["body"]).decode()
    assert page_fetch(browser, "/api/camera/NAO1")["status"] == 400
    # The CLI form.
    out = fleet.tmp / "frame.jpg"
    r = json.loads(fleet.inv("robot", "camera", "--robot", "nao1", "--out", str(out), "--json", check=True).stdout)
    assert (r["width"], r["height"], r["encoding"]) == (320, 240, "rgb8") and jpeg_size(out.read_bytes()) == (320, 240)
    fleet.log.append(f"ccrp robot camera: read in {r['read_ms']} ms, frame {r['age_ms']} ms old on the clone, {r['bytes']} bytes")
    fleet.log.append("ccrp robot camera, human:\n" + fleet.inv("robot", "camera", "--robot", "nao1", "--out", str(out), check=True).stdout)
    refused = fleet.inv("robot", "camera", "--robot", "nao2", "--out", str(fleet.tmp / "none.jpg"), "--timeout", "2")
    assert refused.returncode == 1 and "nothing publishes /camera/image_raw" in refused.stderr, refused.stderr
    assert "Traceback" not in refused.stderr and not (fleet.tmp / "none.jpg").exists()
    # Off: the page stops asking.
    from selenium.webdriver.support.ui import Select

    Select(browser.find_element(By.ID, "camera-robot")).select_by_value("")
    assert not browser.find_element(By.ID, "camera-view").is_displayed()


def test_power_off_and_on_switches_the_simulated_robot(fleet, dashboard, browser):
    sim = fleet.container("robot-sim", "nao1")
    press(browser, "nao1", "button.power", "Power off")
    WebDriverWait(browser, 5).until(lambda d: d.switch_to.alert).accept()  # the confirm() dialog
    wait(browser, "the power-off action reported done", lambda d: any(
        "ccrp robot power off --robot nao1" in li.text for li in d.find_elements(By.CSS_SELECTOR, "#actions li.done")), 60)
    # A power cut leaves no exit notice: once the device reports the robot off, ccrp ends the dead
    # VPN session on the clone, which would otherwise list it until its keepalive dropped it.
    before = cell(browser, "nao1", "vpn")  # connected <address:port> of the session the cut ends
    wait(browser, "nao1 shown powered off, its VPN session ended, with its alert",
         lambda d: cell(d, "nao1", "power") == "off" and cell(d, "nao1", "watchdog").startswith("off")
         and not cell(d, "nao1", "vpn").startswith("connected")
         and d.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="robot-powered-off"][data-robot="nao1"]'), 30)
    for unit in ("ccrp-vpn", "ccrp-watchdog", "ccrp-demo-node"):  # the robot's computer is off...
        assert sim.exec_run(["systemctl", "is-active", unit]).output.decode().strip() != "active", unit
    # ...its power line and its power device are not: the device, a container of its own with the
    # device bundle, still reports to the clone every 3 s through its own tunnel.
    assert sim.exec_run(["systemctl", "is-active", "ccrp-power-supply"]).output.decode().strip() == "active"
    device = fleet.container("power-sim", "nao1")
    for unit in ("ccrp-power-vpn", "ccrp-power-device"):
        assert device.exec_run(["systemctl", "is-active", unit]).output.decode().strip() == "active", unit
    row = fleet.status()["nao1"]
    assert row["power"]["relay"] == "off" and row["power"]["robot"] == "off" and row["power"]["age_s"] <= 4, row["power"]
    assert row["watchdog"]["state"] == "off"
    assert "robot-powered-off" in [a["kind"] for a in row["alerts"]]
    assert "robot-disconnected" not in [a["kind"] for a in row["alerts"]]
    import json

    on = json.loads(fleet.inv("robot", "power", "on", "--robot", "nao1", "--json", check=True).stdout)
    assert on["power"] == "on" and on["robot_state"] == "running" and on["device"] == "simulated", on
    fleet.log.append(f"robot power on: device reported the robot running {on['seconds']} s after the relay was set")
    t0 = time.monotonic()
    for unit in ("ccrp-vpn", "ccrp-watchdog", "ccrp-demo-node"):  # booted again (the node's transient unit too)
        assert sim.exec_run(["systemctl", "is-active", unit]).output.decode().strip() == "active", unit
    wait(browser, "nao1 back: a new VPN session, its node on its clone, its watchdog connected",
         lambda d: cell(d, "nao1", "power") == "on" and cell(d, "nao1", "vpn").startswith("connected")
         and cell(d, "nao1", "vpn") != before
         and "/nao1_demo" in cell(d, "nao1", "nodes") and cell(d, "nao1", "watchdog").startswith("connected since"), 60)
    fleet.log.append(f"power on -> nao1 connected with its node, shown: {time.monotonic() - t0:.1f} s after the report")
    assert not browser.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="robot-powered-off"]')
    status = json.loads(fleet.inv("robot", "power", "status", "--robot", "nao1", "--json", check=True).stdout)
    assert status["power"] == "on"
    refused = fleet.inv("robot", "power", "off", "--robot", "nao2")  # no simulated robot, no device installed
    assert refused.returncode == 2 and "has no power device reporting to its clone" in refused.stderr, refused.stderr


def test_the_power_device_reaches_only_the_power_agent_and_can_be_revoked(fleet):
    """The device's tunnel is its own: the clone's firewall lets its address reach the power agent
    and nothing else; revoked alone, its session ends, its report goes silent, and the robot's own
    session stays."""
    import json

    device = fleet.container("power-sim", "nao1")
    clone_vpn_ip = fleet.plan()["nao1"]["clone_vpn_ip"]
    probe = ("import socket, sys\ntry:\n    socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=3).close()\n"
             "    print('open')\nexcept OSError as e:\n    print(type(e).__name__)")
    reach = lambda port: device.exec_run(["python3", "-c", probe, clone_vpn_ip, str(port)]).output.decode().strip()  # noqa: E731
    assert reach(11400) == "open"
    assert reach(11311) in ("TimeoutError", "timeout")  # the ROS master: dropped for the device
    assert fleet.status()["nao1"]["power"]["silent"] is False
    revoked = json.loads(fleet.inv("vpn", "revoke", "--robot", "nao1", "--cert", "power", "--json", check=True).stdout)
    assert [r["cn"] for r in revoked] == ["nao1.power"]
    row = wait_for("nao1's device silent, nao1 still connected",
                   lambda: ((r := fleet.status()["nao1"])["power"]["silent"] and r["vpn_connected"], r), timeout=40)
    assert row["watchdog"]["state"] == "connected"
    # Its next `robot power` gives the simulated device a new certificate (a real one needs
    # `robot power bundle` on purpose), and it reports again.
    on = json.loads(fleet.inv("robot", "power", "status", "--robot", "nao1", "--json", check=True).stdout)
    assert on["power"] == "on" and not on["silent"], on



def test_revoke_from_the_page_runs_and_reports_through_events(fleet, dashboard, browser, shots):
    press(browser, "nao2", "button.danger", "Revoke")
    WebDriverWait(browser, 5).until(lambda d: d.switch_to.alert).accept()  # the confirm() dialog
    wait(browser, "the revoke action reported done",
         lambda d: any("ccrp vpn revoke --robot nao2" in li.text
                       for li in d.find_elements(By.CSS_SELECTOR, "#actions li.done")), 60)
    item = browser.find_element(By.CSS_SELECTOR, "#actions li.done").text  # the newest first
    assert "ccrp vpn revoke --robot nao2" in item and "nao2 revoked" in item
    wait(browser, "nao2 shown revoked", lambda d: cell(d, "nao2", "vpn").startswith("revoked"), 15)
    assert browser.execute_script("return window.ccrpSamePage") == 42
    assert fleet.status()["nao2"]["revoked_at"]  # as `ccrp status` sees it
    assert browser.save_screenshot(str(shots / "dashboard-revoke.png"))


def dashboard_actions(dashboard, browser) -> list[dict]:
    """The dashboard's actions, read with the browser's session (its cookie)."""
    import json

    return json.loads(browser.execute_script(
        "const r = new XMLHttpRequest(); r.open('GET', '/api/actions', false); r.send(); return r.responseText;"))


def test_a_stopped_clone_is_an_alert_and_start_brings_it_back(fleet, dashboard, browser):
    assert cell(browser, "nao1", "watchdog").startswith("connected since")
    stopped = time.time()
    fleet.container("clone", "nao1").stop(timeout=5)  # as a crash or a cloud console would
    wait(browser, "nao1's clone shown down with an alert",
         lambda d: not cell(d, "nao1", "state").startswith("running")
         and d.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="clone-down"][data-robot="nao1"]'), 30)
    # Its robot's watchdog lost its brain and ran the fallback hook: shown on the page and by status.
    # The watchdog writes its state before it runs the hooks, so the page may show "brainless"
    # with the motors still enabled for a moment: wait for both.
    wait(browser, "nao1 shown brainless, motors stopped, with its alert",
         lambda d: cell(d, "nao1", "watchdog").startswith("brainless since")
         and "(motors stopped)" in cell(d, "nao1", "watchdog")
         and d.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="robot-brainless"][data-robot="nao1"]'), 30)
    row = fleet.status()["nao1"]
    w = row["watchdog"]
    assert w["state"] == "brainless" and w["motors"] == "stopped" and w["source"] == "simulated robot", w
    assert "robot-brainless" in [a["kind"] for a in row["alerts"]]
    lost_after = dt.datetime.fromisoformat(w["since"]).timestamp() - stopped
    assert lost_after <= 7, w  # the default watchdog (2 s x 2 failures) within 6 s; `since` is to the second
    human = fleet.inv("status", check=True).stdout
    assert "brainless since" in human and "alert(s)" in human and "nao1 is brainless since" in human, human
    fleet.log.append(f"clone stopped -> nao1 brainless after {lost_after:.1f} s (robot's clock, 1 s resolution)")
    fleet.log.append("ccrp status, nao1 brainless:\n" + human)
    press(browser, "nao1", "button:not(.danger)", "Start")
    wait(browser, "the start action reported done",
         lambda d: any("ccrp clone start --robot nao1" in li.text
                       for li in d.find_elements(By.CSS_SELECTOR, "#actions li.done")), 90)
    assert "nao1: started" in browser.find_element(By.CSS_SELECTOR, "#actions li.done").text
    wait(browser, "nao1's clone running and its robot back",
         lambda d: cell(d, "nao1", "state").startswith("running") and cell(d, "nao1", "vpn").startswith("connected"), 60)
    assert not browser.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="clone-down"]')
    wait(browser, "nao1's watchdog back to connected",
         lambda d: cell(d, "nao1", "watchdog").startswith("connected since")
         and not d.find_elements(By.CSS_SELECTOR, '#alerts li[data-kind="robot-brainless"]'), 30)
    back = fleet.status()["nao1"]["watchdog"]
    assert back["motors"] == "enabled"  # the hook ran `restored`
    started = next(a for a in dashboard_actions(dashboard, browser) if a["kind"] == "clone-start")
    fleet.log.append("clone start done -> nao1's watchdog restored: "
                     f"{dt.datetime.fromisoformat(back['since']).timestamp() - dt.datetime.fromisoformat(started['ended_at']).timestamp():.0f} s "
                     "(1 s resolution; the clone serves before the action ends)")
    assert browser.execute_script("return window.ccrpSamePage") == 42


def test_scale_from_the_page_adds_a_template_robot(fleet, dashboard, browser):
    size = browser.find_element(By.ID, "scale-size")
    size.clear()
    size.send_keys("3")
    browser.find_element(By.ID, "scale-button").click()
    WebDriverWait(browser, 5).until(lambda d: d.switch_to.alert).accept()
    wait(browser, "the scale action reported done",
         lambda d: any("ccrp fleet scale 3" in li.text for li in d.find_elements(By.CSS_SELECTOR, "#actions li.done")), 120)
    assert "robot1: created" in browser.find_element(By.CSS_SELECTOR, "#actions li.done").text
    wait(browser, "robot1's clone listed running", lambda d: cell(d, "robot1", "state").startswith("running"), 15)
    assert sorted(fleet.status()) == ["nao1", "nao2", "robot1"]
    assert browser.execute_script("return window.ccrpSamePage") == 42


def test_the_token_is_printed_once_and_in_no_log_line(dashboard, shots):
    text = Path(dashboard["log"]).read_text()
    assert text.count(dashboard["token"]) == 1, text
    for line in ('"GET /" 303', '"POST /api/actions/vpn-revoke" 202', '"POST /api/actions/clone-start" 202',
                 '"POST /api/actions/fleet-scale" 202'):
        assert line in text, text
    assert os.path.getsize(shots / "dashboard.png") > 10_000
