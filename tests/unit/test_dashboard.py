"""`ccrp dashboard` without a fleet: who gets in (token, session cookie, Host, Origin, CSRF), that
the token is in no response, event or log line, the alerts, and the event stream of a real server."""

from __future__ import annotations

import base64
import datetime as dt
import json
import logging
import re
import socket
import threading
import time

import pytest

pytest.importorskip("fastapi", reason="the dashboard's web stack (`pip install -e .[dashboard]`) is not installed")
from fastapi.testclient import TestClient  # noqa: E402

from ccrp_cli.dashboard.app import Actions, Teleop, create_app  # noqa: E402
from ccrp_cli.dashboard.auth import Auth, allowed_hosts  # noqa: E402
from ccrp_cli.dashboard.events import Broker, Monitor, pki_alerts, row_alerts  # noqa: E402
from ccrp_cli.models.status import StatusRow  # noqa: E402
from ccrp_cli.dashboard.server import parse_bind  # noqa: E402
from ccrp_cli.errors import InputError  # noqa: E402

TOKEN = "unit-test-token-" + "x" * 27
PORT = 8080
BASE = f"http://127.0.0.1:{PORT}"


def row(robot="nao1", **changes) -> StatusRow:
    base = {"robot": robot, "clone": f"cri-{robot}", "phase": "ready", "status": "running", "state": "running",
            "public_ip": "172.30.0.3", "common_ip": "10.90.0.10", "vpn_subnet": "10.80.1.0/24", "vpn_connected": True,
            "secrets": True, "robot_address": "172.30.0.5:5000", "master_reachable": True, "ros_distro": "noetic",
            "robot_nodes": [f"/{robot}_demo"], "relay_running": True, "relay_peers": {"nao2": True},
            "api_manager": {"running": True, "backend": "opencv", "last_error": "a backend's answer, not for the page"}}
    return StatusRow(**(base | changes))


class Dashboard:
    """The app with a fake fleet: `rows` is what fleet_status returns, `calls` the actions run."""

    def __init__(self, port: int = PORT, interval: float = 0.2) -> None:
        self.rows = [row("nao1"), row("nao2", vpn_connected=False, robot_address=None, robot_nodes=[])]
        self.calls: list[tuple[str, dict]] = []
        self.broker = Broker()
        self.monitor = Monitor(self.broker, lambda: self.rows, lambda robots: [], interval, "lab", "docker")

        def fake(kind):
            def run(args, say):
                self.calls.append((kind, args))
                say(f"working on {args}")
                return [{"robot": args.get("robot", "robot1"), "action": "started", "seconds": 0.1, "detail": ""}]
            return run

        self.actions = Actions(self.broker, {k: fake(k) for k in ("clone-start", "clone-restart", "vpn-revoke", "fleet-scale", "robot-power")},
                               self.monitor.refresh)
        self.sent: list[tuple[str, float, float]] = []
        self.hold = threading.Event()
        self.hold.set()

        def send(robot, linear, angular):
            self.sent.append((robot, linear, angular))
            self.hold.wait(5)
            if robot == "nao2":
                raise InputError("robot 'nao2': nothing subscribes to /cmd_vel on this master")
            return {"robot": robot, "topic": "/cmd_vel", "linear": linear, "angular": angular, "acknowledged": True,
                    "one_way_ms": 3.2, "round_trip_ms": 6.1, "request_ms": 900.0, "attempts": 1}

        self.auth = Auth(TOKEN, port, allowed_hosts("127.0.0.1", port))
        self.app = create_app(self.auth, self.broker, self.monitor, self.actions, "lab", Teleop(send, self.broker))


@pytest.fixture
def dash():
    d = Dashboard()
    with TestClient(d.app, base_url=BASE, follow_redirects=False) as client:
        d.client = client
        yield d


def login(client) -> str:
    r = client.get(f"/?token={TOKEN}")
    assert r.status_code == 303 and r.headers["location"] == "/"
    cookie = r.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and "Path=/" in cookie
    page = client.get("/")
    assert page.status_code == 200
    return re.search(r'name="ccrp-csrf" content="([^"]+)"', page.text).group(1)


ROUTES = [("GET", "/"), ("GET", "/static/app.js"), ("GET", "/events"), ("GET", "/api/status"),
          ("GET", "/api/actions"), ("POST", "/api/actions/clone-start"), ("POST", "/api/teleop"),
          ("GET", "/api/camera/nao1"), ("POST", "/api/camera/nao1/start")]


@pytest.mark.parametrize("method, path", ROUTES)
def test_every_route_is_refused_without_a_session(dash, method, path):
    r = dash.client.request(method, path, headers={"Origin": BASE})
    assert r.status_code == 401
    assert "set-cookie" not in r.headers


def test_a_wrong_token_or_a_forged_cookie_is_refused(dash):
    assert dash.client.get("/?token=" + TOKEN[:-1] + "y").status_code == 401
    for forged in (TOKEN, "guess"):  # the token itself is no session
        dash.client.cookies.set(dash.auth.cookie, forged)
        assert dash.client.get("/").status_code == 401


def test_the_token_opens_a_session_whose_cookie_is_not_the_token(dash):
    login(dash.client)
    assert dash.client.cookies[dash.auth.cookie] != TOKEN
    assert dash.client.get("/api/status").status_code == 200
    assert dash.client.get("/static/app.js").status_code == 200
    assert dash.client.get("/static/../auth.py").status_code in (401, 404)


def test_an_unknown_host_is_refused_even_with_a_session(dash):
    login(dash.client)
    assert dash.client.get("/api/status", headers={"Host": "attacker.example:8080"}).status_code == 403
    assert dash.client.get("/api/status", headers={"Host": f"localhost:{PORT}"}).status_code == 200


def test_post_needs_the_same_origin_and_the_sessions_csrf_token(dash):
    csrf = login(dash.client)
    url, body = "/api/actions/clone-start", {"robot": "nao1"}
    post = dash.client.post
    assert post(url, json=body, headers={"Origin": BASE}).status_code == 403  # no CSRF token
    assert post(url, json=body, headers={"Origin": BASE, "X-CCRP-CSRF": "wrong"}).status_code == 403
    assert post(url, json=body, headers={"Origin": "http://attacker.example", "X-CCRP-CSRF": csrf}).status_code == 403
    assert post(url, json=body, headers={"Origin": "null", "X-CCRP-CSRF": csrf}).status_code == 403
    assert post(url, json=body, headers={"X-CCRP-CSRF": csrf}).status_code == 403  # neither Origin nor Referer
    assert post(url, json=body, headers={"Referer": "http://attacker.example/", "X-CCRP-CSRF": csrf}).status_code == 403
    assert dash.calls == []
    # Another session's CSRF token does not do either.
    other = TestClient(dash.app, base_url=BASE, follow_redirects=False)
    other_csrf = login(other)
    assert post(url, json=body, headers={"Origin": BASE, "X-CCRP-CSRF": other_csrf}).status_code == 403
    r = post(url, json=body, headers={"Origin": BASE, "X-CCRP-CSRF": csrf})
    assert r.status_code == 202, r.text
    assert post(url, json=body, headers={"Referer": BASE + "/", "X-CCRP-CSRF": csrf}).status_code == 202
    deadline = time.monotonic() + 5
    while len([a for a in dash.client.get("/api/actions").json() if a["state"] == "done"]) < 2:
        assert time.monotonic() < deadline, dash.client.get("/api/actions").json()
        time.sleep(0.05)
    assert dash.calls == [("clone-start", {"robot": "nao1"})] * 2


def test_restart_is_ccrp_clone_restart_with_a_checked_robot(dash):
    headers = {"Origin": BASE, "X-CCRP-CSRF": login(dash.client)}
    url = "/api/actions/clone-restart"
    assert dash.client.post(url, json={"robot": "nao1; reboot"}, headers=headers).status_code == 400
    r = dash.client.post(url, json={"robot": "nao1"}, headers=headers)
    assert r.status_code == 202, r.text
    deadline = time.monotonic() + 5
    while not [a for a in dash.client.get("/api/actions").json() if a["state"] == "done"]:
        assert time.monotonic() < deadline, dash.client.get("/api/actions").json()
        time.sleep(0.05)
    done = dash.client.get("/api/actions").json()[-1]
    assert done["title"] == "clone restart --robot nao1" and dash.calls == [("clone-restart", {"robot": "nao1"})]


def test_only_get_head_and_post_exist_and_arguments_are_checked(dash):
    csrf = login(dash.client)
    headers = {"Origin": BASE, "X-CCRP-CSRF": csrf}
    assert dash.client.delete("/api/actions/clone-start", headers=headers).status_code == 405
    assert dash.client.put("/api/actions/clone-start", headers=headers).status_code == 405
    assert dash.client.post("/api/actions/clone-start", json={"robot": "../x"}, headers=headers).status_code == 400
    assert dash.client.post("/api/actions/fleet-scale", json={"size": -1}, headers=headers).status_code == 400
    assert dash.client.post("/api/actions/rm-rf", json={}, headers=headers).status_code == 404
    assert dash.calls == []


def test_the_token_is_in_no_response_and_no_log_line(dash, caplog):
    caplog.set_level(logging.INFO, logger="ccrp.dashboard")
    seen = []
    seen.append(dash.client.get("/"))
    seen.append(dash.client.get(f"/?token={TOKEN}"))
    csrf = login(dash.client)
    for path in ("/", "/static/app.js", "/static/style.css", "/api/status", "/api/actions"):
        seen.append(dash.client.get(path))
    seen.append(dash.client.post("/api/actions/fleet-scale", json={"size": 3}, headers={"Origin": BASE, "X-CCRP-CSRF": csrf}))
    for r in seen:
        assert TOKEN not in r.text and TOKEN not in str(r.headers)
    status = dash.client.get("/api/status").json()
    assert "never-shown" not in json.dumps(status)  # fields outside the status whitelist stay home
    assert caplog.records and all(TOKEN not in rec.getMessage() for rec in caplog.records)
    assert any('"GET /" 303' in rec.getMessage() for rec in caplog.records)


def test_security_headers_on_every_answer(dash):
    for r in (dash.client.get("/"), dash.client.get(f"/?token={TOKEN}")):
        assert "frame-ancestors 'none'" in r.headers["content-security-policy"]
        assert r.headers["x-frame-options"] == "DENY"
        assert r.headers["referrer-policy"] == "no-referrer"


def test_alerts_from_status_rows():
    kinds = lambda r: [a["kind"] for a in row_alerts(r)]  # noqa: E731
    assert kinds(row()) == []
    assert kinds(row(status="exited", state="stopped")) == ["clone-down"]
    assert kinds(row(status="ACTIVE")) == []  # OpenStack's word for a running clone
    assert kinds(row(status="SHUTOFF", state="stopped")) == ["clone-down"]
    assert kinds(row(status="running (unreachable)", unreachable="exec failed: boom")) == ["clone-unreachable"]
    assert kinds(row(status="stopped (idle)")) == ["clone-stopped-idle"]
    assert kinds(row(status="absent", phase="ready")) == ["clone-down"]
    assert kinds(row(status="absent", phase="planned")) == ["clone-absent"]
    assert kinds(row(vpn_connected=False, robot_nodes=[], stale_nodes=["/nao1_demo"])) == ["robot-disconnected"]
    assert "stale nodes on its master: /nao1_demo" in row_alerts(row(vpn_connected=False, stale_nodes=["/nao1_demo"]))[0]["text"]
    assert kinds(row(relay_peers={"nao2": False, "turtlebot1": True})) == ["relay-peer-down"]
    assert kinds(row(relay_running=False)) == ["relay-down"]
    assert kinds(row(master_reachable=False)) == ["master-down"]
    assert kinds(row(revoked_at="2026-01-01T00:00:00+00:00")) == ["revoked-connected"]
    assert kinds(row(revoked_at="2026-01-01T00:00:00+00:00", vpn_connected=False)) == ["robot-revoked"]
    assert kinds(row(secrets=False, vpn_connected=False)) == ["clone-keys-gone", "robot-disconnected"]


def test_certificate_and_crl_expiry_alerts(lab):
    robots = [r.name for r in lab.inventory.robots]
    assert pki_alerts(lab.pki, robots) == []
    crl_left = lab.pki.crl_days_left()
    index = lab.pki.load_index()
    cert_left = min((c.not_after for c in index.certs if c.profile == "client"))
    # Move the clock: the CRL ends first, within the warning window, then within the error one.
    soon = dt.datetime.now(dt.timezone.utc) + dt.timedelta(days=crl_left - 10)
    alerts = pki_alerts(lab.pki, robots, now=soon)
    assert [(a["level"], a["kind"]) for a in alerts if a["kind"] == "crl-expiry"] == [("warning", "crl-expiry")]
    late = cert_left - dt.timedelta(days=3)
    alerts = pki_alerts(lab.pki, robots, now=late)
    certs = {a["text"].split()[2]: a for a in alerts if a["kind"] == "cert-expiry"}
    assert {"nao1", "cri-nao1"} <= set(certs) and certs["nao1"]["level"] == "error"
    assert "ccrp vpn issue-cert --robot nao1 --renew" in certs["nao1"]["text"]
    assert not any("nao1" in a["text"] for a in pki_alerts(lab.pki, ["nao2"], now=late) if a["kind"] == "cert-expiry")


@pytest.mark.parametrize("bind, expected", [
    ("127.0.0.1:8080", ("127.0.0.1", 8080)), ("localhost:0", ("127.0.0.1", 0)), ("[::1]:9000", ("::1", 9000)),
    ("0.0.0.0", ("0.0.0.0", 8080)),
])
def test_bind(bind, expected):
    assert parse_bind(bind) == expected


@pytest.mark.parametrize("bind", ["example.com:80", "127.0.0.1:99999", "127.0.0.1:http", "[::1]x"])
def test_bad_bind_is_bad_input(bind):
    with pytest.raises(InputError):
        parse_bind(bind)


def test_short_token_refused():
    with pytest.raises(InputError):
        Auth("short", PORT, None)


def test_events_reach_an_open_page_without_a_reload():
    """A real server: the page's stream gets the fleet at once, a change at the next poll, and an
    action's progress; no event carries the token."""
    import httpx
    import uvicorn

    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    d = Dashboard(port=port, interval=0.3)
    server = uvicorn.Server(uvicorn.Config(d.app, log_config=None, access_log=False, log_level="warning",
                                           timeout_graceful_shutdown=1))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=base, timeout=10) as client:
            deadline = time.monotonic() + 10
            while not server.started:
                assert time.monotonic() < deadline
                time.sleep(0.05)
            csrf = login(client)
            events, text = [], []
            with client.stream("GET", "/events") as stream:
                assert stream.headers["content-type"].startswith("text/event-stream")
                name = None
                for line in stream.iter_lines():
                    text.append(line)
                    if line.startswith("event: "):
                        name = line[7:]
                    elif line.startswith("data: "):
                        data = json.loads(line[6:])
                        events.append((name, data))
                        if len(events) == 1:  # the fleet at once; then nao2 connects, and an action
                            assert name == "fleet" and not data["rows"][1]["vpn_connected"]
                            assert data["ros2"] is False  # a ROS 1 fleet: the page's column says Master
                            d.rows = [row("nao1"), row("nao2")]
                            r = client.post("/api/actions/fleet-scale", json={"size": 4},
                                            headers={"Origin": base, "X-CCRP-CSRF": csrf})
                            assert r.status_code == 202
                        fleet = [e for n, e in events if n == "fleet"]
                        done = [e for n, e in events if n == "action" and e["state"] == "done"]
                        if fleet[-1]["rows"][1]["vpn_connected"] and done:
                            break
                    assert len(events) < 100, events[-3:]
            assert done[0]["title"] == "fleet scale 4" and done[0]["lines"] == ["working on {'size': 4}"]
            assert all(a["kind"] != "robot-disconnected" for a in fleet[-1]["alerts"])
            assert TOKEN not in "\n".join(text) and "never-shown" not in "\n".join(text)
    finally:
        d.broker.close()
        server.should_exit = True
        thread.join(10)
        sock.close()
    assert not thread.is_alive()


def test_scale_below_the_inventory_changes_nothing(ccrp_home):
    """Bad input from the page or the CLI: one line, before any PKI or snapshot is made (it used to
    build the fleet's snapshot first, and retention then removed an older one)."""
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops.fleet import fleet_scale
    from tests.conftest import LAB

    fleet = Fleet.open(LAB)
    with pytest.raises(InputError, match="names 3 robots in its inventory; cannot scale to 1"):
        fleet_scale(fleet, None, 1, lambda line: pytest.fail(f"said {line!r}"))
    assert not fleet.pki.exists()


def test_teleop_sends_one_command_and_answers_with_its_latency(dash):
    csrf = login(dash.client)
    headers = {"Origin": BASE, "X-CCRP-CSRF": csrf}
    body = {"robot": "nao1", "linear": 0.2, "angular": -0.5}
    assert dash.client.post("/api/teleop", json=body, headers={"Origin": BASE}).status_code == 403  # CSRF
    assert dash.sent == []
    r = dash.client.post("/api/teleop", json=body, headers=headers)
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["ok"] and got["one_way_ms"] == 3.2 and got["round_trip_ms"] == 6.1 and got["linear"] == 0.2
    assert dash.sent == [("nao1", 0.2, -0.5)]
    # A robot that cannot take it: the page gets the reason (502), the server goes on.
    r = dash.client.post("/api/teleop", json=body | {"robot": "nao2"}, headers=headers)
    assert r.status_code == 502 and not r.json()["ok"] and "nothing subscribes" in r.json()["error"]
    for bad in ({"robot": "nao1", "linear": 11, "angular": 0}, {"robot": "nao1", "linear": 0},
                {"robot": "../x", "linear": 0, "angular": 0}, body | {"topic": "/x"}):
        assert dash.client.post("/api/teleop", json=bad, headers=headers).status_code == 400, bad
    r = dash.client.post("/api/teleop", content=b'{"robot": "nao1", "linear": NaN, "angular": 0}',
                         headers=headers | {"Content-Type": "application/json"})
    assert r.status_code == 400
    assert len(dash.sent) == 2


def test_teleop_keeps_one_command_in_flight_per_robot(dash):
    csrf = login(dash.client)
    headers = {"Origin": BASE, "X-CCRP-CSRF": csrf}
    dash.hold.clear()
    first: list = []
    t = threading.Thread(target=lambda: first.append(
        dash.client.post("/api/teleop", json={"robot": "nao1", "linear": 0.2, "angular": 0}, headers=headers)))
    t.start()
    deadline = time.monotonic() + 5
    while not dash.sent:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    r = dash.client.post("/api/teleop", json={"robot": "nao1", "linear": 0, "angular": 0}, headers=headers)
    assert r.status_code == 409
    dash.hold.set()
    t.join(5)
    assert first[0].status_code == 200
    assert dash.sent == [("nao1", 0.2, 0)]
    r = dash.client.post("/api/teleop", json={"robot": "nao1", "linear": 0, "angular": 0}, headers=headers)
    assert r.status_code == 200  # free again


def test_robot_teleop_refuses_bad_input_before_opening_the_fleet(ccrp, tmp_path):
    missing = str(tmp_path / "none.yaml")  # the fleet is never opened: bad input first
    for args in (["--linear", "11"], ["--angular", "nan"], ["--topic", "cmd vel"], ["--topic", "/a//b"]):
        r = ccrp("robot", "teleop", "-i", missing, "--robot", "nao1", *args)
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.startswith("ccrp: error:") and "Traceback" not in r.stderr


def test_power_from_the_page_is_an_action_with_checked_arguments(dash):
    csrf = login(dash.client)
    headers = {"Origin": BASE, "X-CCRP-CSRF": csrf}
    url = "/api/actions/robot-power"
    assert dash.client.post(url, json={"robot": "nao1", "state": "off"}, headers={"Origin": BASE}).status_code == 403
    for bad in ({"robot": "nao1", "state": "reboot"}, {"robot": "nao1"}, {"robot": "../x", "state": "on"},
                {"robot": "nao1", "state": "on", "force": True}):
        assert dash.client.post(url, json=bad, headers=headers).status_code == 400, bad
    r = dash.client.post(url, json={"robot": "nao1", "state": "off"}, headers=headers)
    assert r.status_code == 202 and r.json()["title"] == "robot power off --robot nao1"
    deadline = time.monotonic() + 5
    while not any(a["state"] == "done" for a in dash.client.get("/api/actions").json()):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    assert dash.calls == [("robot-power", {"robot": "nao1", "state": "off"})]


ASK = ["python3", "-c"]  # the camera's client (camera.ASK_ARGV): a read, never a start

# A real JPEG (16x8), as the clone's OpenCV would send one.
JPEG = base64.b64decode(
    "/9j/4AAQSkZJRgABAQAAAQABAAD/2wBDABALDA4MChAODQ4SERATGCgaGBYWGDEjJR0oOjM9PDkzODdASFxOQERXRTc4UG1RV19iZ2hnPk1xeXBkeFxlZ2P/2wBDARESEhgVGC8aGi9jQjhCY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2NjY2P/wAARCAAIABADASIAAhEBAxEB/8QAHwAAAQUBAQEBAQEAAAAAAAAAAAECAwQFBgcICQoL/8QAtRAAAgEDAwIEAwUFBAQAAAF9AQIDAAQRBRIhMUEGE1FhByJxFDKBkaEII0KxwRVS0fAkM2JyggkKFhcYGRolJicoKSo0NTY3ODk6Q0RFRkdISUpTVFVWV1hZWmNkZWZnaGlqc3R1dnd4eXqDhIWGh4iJipKTlJWWl5iZmqKjpKWmp6ipqrKztLW2t7i5usLDxMXGx8jJytLT1NXW19jZ2uHi4+Tl5ufo6erx8vP09fb3+Pn6/8QAHwEAAwEBAQEBAQEBAQAAAAAAAAECAwQFBgcICQoL/8QAtREAAgECBAQDBAcFBAQAAQJ3AAECAxEEBSExBhJBUQdhcRMiMoEIFEKRobHBCSMzUvAVYnLRChYkNOEl8RcYGRomJygpKjU2Nzg5OkNERUZHSElKU1RVVldYWVpjZGVmZ2hpanN0dXZ3eHl6goOEhYaHiImKkpOUlZaXmJmaoqOkpaanqKmqsrO0tba3uLm6wsPExcbHyMnK0tPU1dbX2Nna4uPk5ebn6Onq8vP09fb3+Pn6/9oADAMBAAIRAxEAPwChRRRXQfRH/9k=")


class CameraClones:
    """The provider boundary: nao1's clone has a camera frame, nao2's robot is not connected,
    turtlebot1 has no clone. `hold` keeps nao1's read running until set. The camera agent serves
    (`serving`) until a test says it does not; its unit's systemd-run starts it."""

    def __init__(self) -> None:
        self.ran: list[tuple[str, list[str]]] = []
        self.pushed: list[str] = []
        self.serving = True
        self.hold = threading.Event()
        self.hold.set()
        self.reply = {"topic": "/camera/image_raw", "width": 16, "height": 8, "encoding": "rgb8", "seq": 41,
                      "frame_id": "nao1_camera", "stamp": 1700000000.25, "age_ms": 12.5,
                      "jpeg": base64.b64encode(JPEG).decode()}

    def query(self):
        return {"nao1": object(), "nao2": object()}

    transport = property(lambda self: self)  # a fake clone is its own transport
    def push_files(self, robot, files, restart=()):
        self.pushed += [f.dest for f in files]

    def exec(self, robot, argv, timeout=60):
        self.ran.append((robot, argv))
        if argv[0] == "systemd-run":
            self.serving = True
        if argv[0] in ("systemd-run", "systemctl"):
            return 0, ""
        self.hold.wait(5)
        if not self.serving:
            return 0, json.dumps({"error": "no camera agent serves ([Errno 2] No such file or directory)", "why": "no-agent"})
        if robot == "nao2":
            out = {"error": "nothing publishes /camera/image_raw on the clone's master (is the robot connected, with a camera?)",
                   "why": "no-publisher"}
        else:
            out = self.reply
        return 0, "[WARN] rospy noise\n" + json.dumps(out) + "\n"


@pytest.fixture
def cam(lab_up, monkeypatch):
    """The app with the camera functions `ccrp dashboard` wires (server.camera_functions), on a
    fake clone at the provider boundary."""
    from ccrp_cli.dashboard.app import Camera
    from ccrp_cli.dashboard.server import camera_functions
    from ccrp_cli.fleet import Fleet
    from tests.conftest import LAB

    d = Dashboard()
    d.clones = CameraClones()
    d.app = create_app(d.auth, d.broker, d.monitor, d.actions, "lab", None, Camera(*camera_functions(Fleet.open(LAB), d.clones)))
    with TestClient(d.app, base_url=BASE, follow_redirects=False) as client:
        d.client = client
        yield d


def test_camera_frame_is_the_clones_jpeg_read_through_exec(cam):
    from ccrp_cli.robot import camera

    assert cam.client.get("/api/camera/nao1").status_code == 401 and cam.clones.ran == []  # no session
    login(cam.client)
    r = cam.client.get("/api/camera/nao1")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/jpeg" and r.headers["cache-control"] == "no-store"
    assert r.content == JPEG
    assert (r.headers["x-ccrp-frame-size"], r.headers["x-ccrp-frame-encoding"], r.headers["x-ccrp-frame-seq"],
            r.headers["x-ccrp-frame-age-ms"], r.headers["x-ccrp-frame-stamp"]) == ("16x8", "rgb8", "41", "12.5", "1700000000.250")
    assert float(r.headers["x-ccrp-frame-read-ms"]) >= 0
    assert "content-security-policy" in r.headers
    (robot, argv), = cam.clones.ran
    # argv, never a shell string with a name in it: the constant client and socket, then the values.
    assert robot == "nao1" and argv == [*camera.ASK_ARGV, "/camera/image_raw", "3"]
    assert not any("nao1" in a for a in argv)


def test_camera_refuses_bad_names_and_says_why_there_is_no_frame(cam):
    login(cam.client)
    for bad in ("NAO1", "a_b", "-x", "x" * 64, "%2E%2E", "n%20a"):
        r = cam.client.get(f"/api/camera/{bad}")
        assert r.status_code == 400 and "bad robot name" in r.json()["error"], bad
    assert cam.client.get("/api/camera/a/b").status_code == 404
    assert cam.clones.ran == []
    r = cam.client.get("/api/camera/ghost")  # not a robot of this fleet
    assert r.status_code == 404 and "ghost" in r.json()["error"]
    r = cam.client.get("/api/camera/nao2")  # its robot is not connected: nothing publishes the camera
    assert r.status_code == 503 and r.headers["cache-control"] == "no-store"
    assert r.json()["why"] == "no-publisher" and "nothing publishes /camera/image_raw" in r.json()["error"]
    r = cam.client.get("/api/camera/turtlebot1")  # no clone
    assert r.status_code == 503 and r.json()["why"] == "no-clone" and "has no clone" in r.json()["error"]
    assert [robot for robot, _ in cam.clones.ran] == ["nao2"]
    cam.clones.reply = {**cam.clones.reply, "jpeg": base64.b64encode(b"<html>not a picture</html>").decode()}
    r = cam.client.get("/api/camera/nao1")
    assert r.status_code == 503 and "sent no JPEG" in r.json()["error"]


def started_units(clones) -> list[list[str]]:
    return [argv for _, argv in clones.ran if argv[0] == "systemd-run"]


def test_a_camera_get_starts_nothing_on_the_clone(cam):
    """A GET is what any page can make the browser send with the session cookie (an <img src>):
    it started the camera agent's unit on the clone. Now a read without an agent is a 503 that
    says so, and nothing was pushed or started."""
    login(cam.client)
    cam.clones.serving = False
    r = cam.client.get("/api/camera/nao1", headers={"Origin": "http://attacker.example"})  # a GET is not checked for Origin
    assert r.status_code == 503 and r.headers["cache-control"] == "no-store", r.text
    assert cam.client.head("/api/camera/nao1").status_code in (405, 503)
    assert r.json()["why"] == "no-agent" and "no camera agent runs on the clone of 'nao1'" in r.json()["error"]
    assert started_units(cam.clones) == [] and cam.clones.pushed == [] and not cam.clones.serving
    assert all(argv[:len(ASK)] == ASK for _, argv in cam.clones.ran)  # reads only


def test_the_camera_agent_starts_with_a_guarded_post(cam):
    """The Camera button's POST: under the Origin and CSRF checks of every POST; it starts the agent
    (as the `ros` user) once, then finds it running; the page's GETs then read frames."""
    from ccrp_cli.robot import camera

    csrf = login(cam.client)
    cam.clones.serving = False
    url = "/api/camera/nao1/start"
    for headers in ({"Origin": BASE}, {"Origin": BASE, "X-CCRP-CSRF": "wrong"},
                    {"Origin": "http://attacker.example", "X-CCRP-CSRF": csrf}, {"X-CCRP-CSRF": csrf}):
        assert cam.client.post(url, headers=headers).status_code == 403, headers
    assert cam.clones.ran == []
    headers = {"Origin": BASE, "X-CCRP-CSRF": csrf}
    r = cam.client.post(url, headers=headers)
    assert r.status_code == 200 and r.json() == {"robot": "nao1", "agent": "started"}, r.text
    (unit,) = started_units(cam.clones)
    assert unit[unit.index("--unit") + 1] == camera.UNIT and "User=ros" in unit and cam.clones.pushed == [camera.AGENT]
    assert cam.client.get("/api/camera/nao1").content == JPEG
    r = cam.client.post(url, headers=headers)
    assert r.json() == {"robot": "nao1", "agent": "running"} and len(started_units(cam.clones)) == 1
    for bad in ("NAO1", "x" * 64):
        assert cam.client.post(f"/api/camera/{bad}/start", headers=headers).status_code == 400
    assert cam.client.post("/api/camera/ghost/start", headers=headers).status_code == 404
    r = cam.client.post("/api/camera/turtlebot1/start", headers=headers)
    assert r.status_code == 503 and r.json()["why"] == "no-clone"
    assert len(started_units(cam.clones)) == 1


def test_camera_runs_one_read_per_robot_at_a_time(cam):
    """Two pages polling one robot: the second request waits for the read under way."""
    login(cam.client)
    cam.clones.hold.clear()
    got: list = []
    threads = [threading.Thread(target=lambda: got.append(cam.client.get("/api/camera/nao1"))) for _ in range(2)]
    threads[0].start()
    deadline = time.monotonic() + 5
    while not cam.clones.ran:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    threads[1].start()
    time.sleep(0.3)  # the second request has reached the server and waits
    cam.clones.hold.set()
    for t in threads:
        t.join(5)
    assert [r.status_code for r in got] == [200, 200] and all(r.content == JPEG for r in got)
    assert len(cam.clones.ran) == 1
    assert cam.client.get("/api/camera/nao1").status_code == 200 and len(cam.clones.ran) == 2  # done: a new read


def test_robot_camera_refuses_bad_input_before_opening_the_fleet(ccrp, tmp_path):
    missing = str(tmp_path / "none.yaml")
    for args in (["--topic", "camera image"], ["--topic", "/a//b"], ["--timeout", "0"]):
        r = ccrp("robot", "camera", "-i", missing, "--robot", "nao1", "--out", str(tmp_path / "f.jpg"), *args)
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.startswith("ccrp: error:") and "Traceback" not in r.stderr
    assert not (tmp_path / "f.jpg").exists()


def test_robot_camera_writes_the_frame(lab_up, tmp_path, monkeypatch):
    """The CLI's body on a fake clone: the JPEG written, its details printed."""
    from typer.testing import CliRunner

    from ccrp_cli import providers
    from ccrp_cli.cli.main import app
    from tests.conftest import LAB

    clones = CameraClones()
    monkeypatch.setattr(providers, "get_provider", lambda inventory: clones)
    out = tmp_path / "frame.jpg"
    r = CliRunner().invoke(app, ["robot", "camera", "-i", str(LAB), "--robot", "nao1", "--out", str(out), "--json"])
    assert r.exit_code == 0, r.output
    assert out.read_bytes() == JPEG
    got = json.loads(r.stdout)
    assert got["width"] == 16 and got["bytes"] == len(JPEG) and got["out"] == str(out) and "jpeg" not in got


def test_the_page_gets_every_row_field_it_reads():
    """A field the page reads but the whitelist leaves out is always undefined there (the Start and
    Restart buttons followed `state`, which no row carried)."""
    from importlib import resources

    from ccrp_cli.dashboard.events import ROW_FIELDS, public_row

    script = resources.files("ccrp_cli.dashboard").joinpath("static", "app.js").read_text()
    read = set(re.findall(r"\brow\.([a-z_]+)", script))
    assert {"state", "robot_rtt_ms", "vpn_connected"} <= read
    assert read <= set(ROW_FIELDS) | {"unreachable"}, read - set(ROW_FIELDS)
    assert public_row(row(state="stopped", robot_rtt_ms=1.5))["state"] == "stopped"
    assert "api_manager" not in public_row(row())  # not in the whitelist: never on the page
    assert public_row(row(unreachable="exec failed: boom"))["unreachable"] is True  # whether, not the error


def test_the_guard_closes_a_websocket_before_any_app_sees_it_and_lets_lifespan_through():
    """The guard checked HTTP only and handed any other scope to the app: a websocket route added
    one day would have had no session, Host or Origin check. Now a websocket is closed (1008, a 403
    to the client) before the app runs, session or not; the lifespan still reaches the app."""
    from starlette.websockets import WebSocketDisconnect

    from ccrp_cli.dashboard.auth import Guard

    seen = []

    async def probe(scope, receive, send):  # would accept any websocket
        seen.append(scope["type"])
        if scope["type"] == "lifespan":
            while (await receive())["type"] != "lifespan.shutdown":
                await send({"type": "lifespan.startup.complete"})
            await send({"type": "lifespan.shutdown.complete"})
        elif scope["type"] == "websocket":
            await receive()
            await send({"type": "websocket.accept"})
            await send({"type": "websocket.send", "text": "fleet"})

    auth = Auth(TOKEN, PORT, allowed_hosts("127.0.0.1", PORT))
    with TestClient(Guard(probe, auth), base_url=BASE) as client:
        with pytest.raises(WebSocketDisconnect) as closed, \
                client.websocket_connect("/events", headers={"Origin": BASE}) as ws:
            ws.receive_text()
        assert closed.value.code == 1008
    assert seen == ["lifespan"]


def test_a_websocket_to_the_dashboard_is_refused_even_with_a_session(dash):
    from starlette.websockets import WebSocketDisconnect

    login(dash.client)
    for path in ("/events", "/", "/api/status"):
        with pytest.raises(WebSocketDisconnect) as closed, dash.client.websocket_connect(path, headers={"Origin": BASE}):
            pass
        assert closed.value.code == 1008, path


class Clock:
    """A monotonic clock the test moves."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_a_session_ends_after_30_idle_minutes_and_after_12_hours_in_any_case(dash):
    from ccrp_cli.dashboard import auth

    assert (auth.SESSION_IDLE_S, auth.SESSION_MAX_S) == (30 * 60, 12 * 3600)  # the documented defaults
    dash.auth.clock = clock = Clock()
    login(dash.client)
    for _ in range(3):  # each request starts the idle time again
        clock.now += auth.SESSION_IDLE_S - 1
        assert dash.client.get("/api/status").status_code == 200
    clock.now += auth.SESSION_IDLE_S
    assert dash.client.get("/api/status").status_code == 401
    assert dash.client.get("/api/status").status_code == 401  # gone, not only late
    # Busy all along: still over after 12 hours.
    login(dash.client)
    opened = clock.now
    while clock.now + 600 < opened + auth.SESSION_MAX_S:
        clock.now += 600
        assert dash.client.get("/api/status").status_code == 200
    clock.now = opened + auth.SESSION_MAX_S
    assert dash.client.get("/api/status").status_code == 401
    login(dash.client)  # the token opens a new one
    assert dash.client.get("/api/status").status_code == 200


def test_an_event_stream_ends_with_its_session(dash):
    """The stream outlived its session: a page left open kept receiving the fleet for ever."""
    from ccrp_cli.dashboard import auth

    dash.auth.clock = clock = Clock()
    login(dash.client)
    events = 0
    with dash.client.stream("GET", "/events") as stream:
        for line in stream.iter_lines():
            if line.startswith("event: fleet"):
                events += 1
                if events == 2:  # the monitor publishes every 0.2 s: the next one ends it
                    clock.now += auth.SESSION_IDLE_S
            assert events < 30, "the stream went on after its session expired"
    assert events >= 2
    assert dash.client.get("/events").status_code == 401  # the page's reconnection is told


def test_logout_is_a_guarded_post_that_ends_the_session(dash):
    csrf = login(dash.client)
    assert 'id="logout"' in dash.client.get("/").text  # the page's button
    sid = dash.client.cookies[dash.auth.cookie]
    session = dash.auth.session(sid)
    # Under the checks of every POST: a foreign page cannot log the operator out either.
    assert dash.client.post("/api/logout", headers={"Origin": BASE}).status_code == 403
    assert dash.client.post("/api/logout", headers={"Origin": "http://attacker.example",
                                                    "X-CCRP-CSRF": csrf}).status_code == 403
    assert dash.client.get("/api/status").status_code == 200
    r = dash.client.post("/api/logout", headers={"Origin": BASE, "X-CCRP-CSRF": csrf})
    assert r.status_code == 204
    cleared = r.headers["set-cookie"]
    assert cleared.startswith(f"{dash.auth.cookie}=") and "Max-Age=0" in cleared and "HttpOnly" in cleared
    assert dash.auth.cookie not in dash.client.cookies
    # The old cookie, kept anyway, is worth nothing: the server forgot the session, and its
    # event streams end (auth.alive).
    old = {"Cookie": f"{dash.auth.cookie}={sid}"}
    assert dash.client.get("/api/status", headers=old).status_code == 401
    assert dash.client.post("/api/logout", headers=old | {"Origin": BASE, "X-CCRP-CSRF": csrf}).status_code == 401
    assert not dash.auth.alive(session)
    login(dash.client)
    assert dash.client.get("/api/status").status_code == 200


def test_wrong_tokens_are_limited_per_client_address(dash, caplog):
    from ccrp_cli.dashboard import auth

    caplog.set_level(logging.INFO, logger="ccrp.dashboard")
    assert (auth.TOKEN_FAILURES_ALLOWED, auth.TOKEN_FAILURE_WINDOW_S) == (5, 60)
    dash.auth.clock = clock = Clock()
    wrong = "/?token=" + TOKEN[:-1] + "y"
    for _ in range(10):  # a success is no failure
        login(dash.client)
    for _ in range(4):
        assert dash.client.get(wrong).status_code == 401
    login(dash.client)
    assert dash.client.get(wrong).status_code == 401  # the fifth within the minute
    # Now even the right token waits: an answer would tell a guesser it is right.
    for waited, retry in ((0, 60), (30, 30), (29, 1)):
        clock.now += waited
        r = dash.client.get(f"/?token={TOKEN}")
        assert r.status_code == 429 and r.headers["retry-after"] == str(retry), (waited, r.headers)
        assert "set-cookie" not in r.headers and TOKEN not in r.text
    assert any("5 wrong tokens" in rec.getMessage() for rec in caplog.records)
    other = TestClient(dash.app, base_url=BASE, follow_redirects=False, client=("192.0.2.7", 50000))
    login(other)  # another address is not held up
    clock.now += 1  # a minute after the first of the five
    login(dash.client)


@pytest.mark.parametrize("token, why", [
    ("a" * 16, "only 1 different characters"), ("ab" * 16, "only 2 different characters"),
    ("0123" * 4, "only 4 different characters"), ("x7Kq", "has 4 characters"),
])
def test_a_weak_token_is_refused_in_one_line_before_the_fleet_is_opened(ccrp, tmp_path, token, why):
    """16 identical characters passed the length check. A weak token is refused before anything
    else (the inventory here does not exist), in one line that does not repeat it."""
    from ccrp_cli.dashboard.auth import MIN_TOKEN_DISTINCT, check_token, new_token

    assert MIN_TOKEN_DISTINCT == 8
    r = ccrp("dashboard", "-i", str(tmp_path / "none.yaml"), "--token", token)
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("ccrp: error:") and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert why in r.stderr and "hint: leave --token out" in r.stderr and "Traceback" not in r.stderr
    assert token not in r.stderr
    with pytest.raises(InputError, match=why):
        Auth(token, PORT, None)
    check_token(new_token())
    check_token("0123456789abcdef")
    check_token("01234567" * 2)


@pytest.mark.parametrize("host, loud", [
    ("0.0.0.0", True), ("::", True), ("192.0.2.10", True), ("fd00::5", True),
    ("127.0.0.1", False), ("127.0.0.2", False), ("::1", False),
])
def test_a_bind_beyond_loopback_warns_that_token_and_cookie_cross_in_clear(host, loud, capsys):
    """It said only that others "may try the token": not that the dashboard speaks plain HTTP, so
    the token and every request's session cookie can be read on the way."""
    from ccrp_cli.dashboard.server import warn_if_exposed

    warn_if_exposed(host)
    out = capsys.readouterr()
    assert out.out == ""
    if not loud:
        assert out.err == ""
        return
    assert out.err.startswith("ccrp: warning:") and out.err.count("\n") == 1, out.err
    assert host in out.err and "without TLS" in out.err
    assert "token and the session cookie cross the network in clear" in out.err
    assert "SSH tunnel" in out.err and "reverse proxy with TLS" in out.err


def test_each_page_action_closes_the_provider_it_opened_even_when_it_fails(lab_up, monkeypatch):
    """A dashboard runs for days: an action's provider (a cloud's SSH sessions) must not outlive it."""
    from ccrp_cli import providers
    from ccrp_cli.dashboard.server import fleet_actions
    from ccrp_cli.errors import CcrpError
    from tests.conftest import LAB

    opened: list = []

    class Unreachable:
        max_parallel = 1

        def __init__(self):
            self.closed = False
            opened.append(self)

        def close(self):
            self.closed = True

        def __getattr__(self, name):  # any use of it: the cloud does not answer
            raise CcrpError("the cloud does not answer")

    monkeypatch.setattr(providers, "get_provider", lambda inventory: Unreachable())
    actions = fleet_actions(LAB)
    for name, args in (("clone-start", {"robot": "nao1"}), ("clone-restart", {"robot": "nao1"}),
                       ("fleet-scale", {"size": 3})):
        with pytest.raises(CcrpError):
            actions[name](args, lambda line: None)
    assert len(opened) == 3 and all(p.closed for p in opened)

