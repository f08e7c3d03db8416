"""A robot's power device: its own certificate and password (checked with openssl), its bundle,
and the clone's power agent talking with the device's agent over real sockets on loopback."""

from __future__ import annotations

import json
import os
import runpy
import shlex
import shutil
import socket
import subprocess
import sys
import threading
import time

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from tests.conftest import ROOT
from tests.unit.helpers import openssl_verify


def test_the_device_has_a_certificate_and_password_of_its_own(lab):
    from ccrp_cli.ops import vpn
    from ccrp_cli.pki.store import RobotRevoked

    pki, v = lab.pki, lab.inventory.vpn
    before = pki.credentials("nao1")
    assert before.power_cert_pem is None
    rec, new = pki.issue_power("nao1", v.cert_days, v.crl_days)
    assert new and rec.cn == "nao1.power" and rec.profile == "power"
    assert pki.issue_power("nao1", v.cert_days, v.crl_days) == (rec, False)  # idempotent
    creds = pki.credentials("nao1")
    cert = x509.load_pem_x509_certificate(creds.power_cert_pem.encode())
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "nao1.power"
    assert list(cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value) == [ExtendedKeyUsageOID.CLIENT_AUTH]
    assert openssl_verify(pki.root, pki.root / rec.cert_path).returncode == 0
    assert creds.power_password != creds.password and creds.power_key_pem != creds.client_key_pem
    assert (pki.root / rec.key_path).stat().st_mode & 0o777 == 0o600
    # The clone's passwd names both, each with its own hash.
    from ccrp_cli.fleet import clone_view
    from ccrp_cli.render.bundles import passwd_file

    lines = passwd_file(clone_view(lab, lab.load_allocated(), "nao1"), creds).content.splitlines()
    assert [line.split(":")[0] for line in lines] == ["nao1", "nao1.power"]
    # Revoking the robot revokes its device (on the robot's power line: who holds one holds both).
    revoked = vpn.revoke(lab, "nao1")
    assert sorted(r["cn"] for r in revoked) == ["nao1", "nao1.power"]
    assert openssl_verify(pki.root, pki.root / rec.cert_path, crl_check=True).returncode != 0
    with pytest.raises(RobotRevoked):
        pki.issue_power("nao1", v.cert_days, v.crl_days)
    # Back in on purpose, the device needs a new certificate: the old one stays revoked.
    vpn.issue(lab, "nao1")
    assert pki.credentials("nao1").power_cert_pem is None
    again, new = pki.issue_power("nao1", v.cert_days, v.crl_days)
    assert new and again.serial != rec.serial
    # The device alone.
    assert [r["cn"] for r in vpn.revoke(lab, "nao1", cert="power")] == ["nao1.power"]
    assert pki.revoked_since("nao1") is None and pki.credentials("nao1").power_cert_pem is None


def test_the_device_bundle_dials_the_clone_as_the_device(lab, tmp_path):
    from ccrp_cli.robot import power

    files, endpoint = power.device_files(lab, "nao1", remote="203.0.113.10")
    by = {f.name: f for f in files}
    creds = lab.pki.credentials("nao1")
    profile = by["power.ovpn"].content
    assert endpoint == "203.0.113.10:1194" and "remote 203.0.113.10 1194" in profile
    assert "\ndev ccrppwr\n" in profile and "auth-user-pass /etc/ccrp/power-credentials" in profile
    assert creds.power_key_pem.strip() in profile and creds.client_key_pem.strip() not in profile
    assert "verify-x509-name cri-nao1 name" in profile  # the device checks the clone, as the robot does
    assert by["power-credentials"].content == f"nao1.power\n{creds.power_password}\n"
    assert creds.password not in "".join(f.content for f in files)
    assert {n: f.mode for n, f in by.items() if f.mode == 0o600}.keys() == {"power.ovpn", "power-credentials"}
    plan = lab.plan(lab.load_allocated())["nao1"]
    assert by["power.env"].content == f"CCRP_POWER_CLONE={plan.clone_vpn_ip}\nCCRP_POWER_PORT=11400\n"
    # install.sh into a staging root, twice: the owner's lines of power.env stay.
    bundle = tmp_path / "bundle"
    from ccrp_cli.render.bundles import write_bundle

    write_bundle(bundle, files, {"robot": "nao1"})
    root = tmp_path / "root"
    env = {"PATH": os.environ["PATH"], "CCRP_ROOT": str(root)}
    assert subprocess.run(["sh", str(bundle / "install.sh")], env=env, capture_output=True).returncode == 0
    with (root / "etc/ccrp/power.env").open("a") as fh:
        fh.write("CCRP_POWER_RELAY_COMMAND=/usr/local/bin/relay-gpio 17\n")
    done = subprocess.run(["sh", str(bundle / "install.sh")], env=env, capture_output=True, text=True)
    assert done.returncode == 0 and "reports to cri-nao1" in done.stdout
    lines = (root / "etc/ccrp/power.env").read_text().splitlines()
    assert sorted(lines) == sorted(["CCRP_POWER_RELAY_COMMAND=/usr/local/bin/relay-gpio 17",
                                    f"CCRP_POWER_CLONE={plan.clone_vpn_ip}", "CCRP_POWER_PORT=11400"])
    assert (root / "etc/ccrp/power.ovpn").stat().st_mode & 0o777 == 0o600
    assert (root / "etc/systemd/system/ccrp-power-device.service").exists()


@pytest.fixture
def agents(tmp_path, monkeypatch):
    """The clone's power agent serving on 127.0.0.1 for a device at 127.0.0.1, and the device
    agent's functions (templates/edge/ccrp-power-device)."""
    from ccrp_cli.agent import power as clone_agent

    monkeypatch.setattr(clone_agent, "WANT", str(tmp_path / "want"))
    monkeypatch.setattr(clone_agent, "REPORT", str(tmp_path / "report"))
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    threading.Thread(target=clone_agent.serve, args=(server, "127.0.0.1"), daemon=True).start()
    device = runpy.run_path(str(ROOT / "templates/edge/ccrp-power-device"), run_name="ccrp_power_device")
    cfg = {"CCRP_POWER_CLONE": "127.0.0.1", "CCRP_POWER_PORT": str(server.getsockname()[1])}
    yield device, cfg, tmp_path
    server.close()


def test_the_device_reports_and_switches_as_the_clone_asks(agents):
    device, cfg, tmp = agents
    report = lambda: json.loads((tmp / "report").read_text())  # noqa: E731
    relay = str(tmp / "relay")
    assert device["relay_state"](relay) == "on"  # never switched: the robot's power is on
    assert device["exchange"](cfg, {"relay": "on", "robot": "running", "t": 1.0}) is None  # nothing asked
    got = report()
    assert (got["relay"], got["robot"], got["device_t"]) == ("on", "running", 1.0) and abs(got["t"] - time.time()) < 5
    (tmp / "want").write_text("off\n")  # what `ccrp robot power off` writes on the clone
    assert device["exchange"](cfg, {"relay": "on", "robot": "running", "t": 2.0}) == "off"
    device["switch"](cfg, relay, "off")
    assert device["relay_state"](relay) == "off"
    assert device["robot_state"](cfg, "off") == "off" and device["robot_state"](cfg, "on") == "running"
    # A relay driven by a command (a GPIO helper): the switch counts only when it succeeds.
    marker = tmp / "gpio"
    ok = {**cfg, "CCRP_POWER_RELAY_COMMAND": shlex.join([sys.executable, "-c",
                                                         f"import sys; open({str(marker)!r}, 'w').write(sys.argv[1])"])}
    device["switch"](ok, relay, "on")
    assert marker.read_text() == "on" and device["relay_state"](relay) == "on"
    with pytest.raises(OSError, match="exited 1"):
        device["switch"]({**cfg, "CCRP_POWER_RELAY_COMMAND": shutil.which("false")}, relay, "off")
    assert device["relay_state"](relay) == "on"
    # The robot's state from a command (a simulated robot's power line file, a ping on a real one).
    assert device["robot_state"]({"CCRP_POWER_ROBOT_COMMAND": "echo starting"}, "on") == "starting"
    assert device["robot_state"]({"CCRP_POWER_ROBOT_COMMAND": "echo nonsense"}, "on") == "starting"


def no_answer(conn) -> bool:
    """Closed without an answer (or reset: the agent closed with what was sent unread)."""
    try:
        return conn.recv(100) == b""
    except ConnectionResetError:
        return True


def test_the_clone_agent_answers_only_its_device_and_only_reports(agents):
    device, cfg, tmp = agents
    port = int(cfg["CCRP_POWER_PORT"])
    # Another address (the firewall already drops it on a clone): no answer, nothing kept.
    with socket.socket() as other:
        other.bind(("127.0.0.2", 0))
        other.settimeout(3)
        other.connect(("127.0.0.1", port))
        other.sendall(b'{"relay": "on", "robot": "running", "t": 1}\n')
        assert no_answer(other)
    assert not (tmp / "report").exists()
    for bad in (b'{"relay": "maybe", "robot": "running", "t": 1}\n', b"not json\n", b"x" * 5000):
        with socket.create_connection(("127.0.0.1", port), timeout=3) as conn:
            conn.sendall(bad)
            assert no_answer(conn), bad
    assert not (tmp / "report").exists()
    assert device["exchange"](cfg, {"relay": "off", "robot": "off", "t": 3.0}) is None  # still serving
    assert json.loads((tmp / "report").read_text())["relay"] == "off"


@pytest.mark.parametrize("bad", [
    b"[" * 1000,  # json's RecursionError
    b'{"relay": "on", "robot": "running", "t": 1' + b"0" * 400 + b"}",  # an int no float holds (OverflowError)
    b'{"relay": "on", "robot": "running", "t": NaN}', b'{"relay": "on", "robot": "running", "t": Infinity}',
    b'{"relay": "on", "robot": "running", "t": true}', b'{"relay": "on", "robot": "running", "t": "1.5"}',
    b'{"relay": ["on"], "robot": "running"}', b'["on", "running"]', b'"on"',
])
def test_a_malformed_report_is_dropped_and_the_agent_keeps_serving(agents, capsys, bad):
    """Whoever holds the device's key and password writes the report line: one that is not a
    report (whatever json makes of it) is dropped and logged, and the next good report is served."""
    device, cfg, tmp = agents
    with socket.create_connection(("127.0.0.1", int(cfg["CCRP_POWER_PORT"])), timeout=3) as conn:
        conn.sendall(bad + b"\n")
        assert no_answer(conn)
    assert not (tmp / "report").exists()
    assert device["exchange"](cfg, {"relay": "off", "robot": "off", "t": 3.0}) is None  # still serving
    assert json.loads((tmp / "report").read_text())["device_t"] == 3.0
    assert "ccrp-power: a report from 127.0.0.1 refused: " in capsys.readouterr().err


def test_roots_wish_goes_through_no_link_the_agents_user_planted(tmp_path, monkeypatch):
    """`ccrp robot power` writes the wish as root in /run/ccrp-power, which the power agent's user
    owns: a link that user put where root writes (the temporary file's old name, or the wish
    itself) must not carry root's write to another file. The agent still reads the wish."""
    from ccrp_cli.robot import power
    from ccrp_cli.agent import power as clone_agent

    run = tmp_path / "ccrp-power"
    run.mkdir()
    victim = tmp_path / "shadow"
    victim.write_text("root's file\n")
    (run / "want.tmp").symlink_to(victim)
    want = run / "want"
    want.symlink_to(victim)
    argv = [*power.SET_STATE, str(want), "off"]
    argv[0] = sys.executable if "python" in argv[0] else argv[0]  # the clone's /usr/bin/python3; here, this one
    done = subprocess.run(argv, capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0 and done.stdout.strip().isdigit(), done.stderr
    assert victim.read_text() == "root's file\n"
    assert not want.is_symlink() and want.read_text() == "off\n" and want.stat().st_mode & 0o777 == 0o644
    assert sorted(p.name for p in run.iterdir()) == ["want", "want.tmp"]  # no temporary file left behind
    monkeypatch.setattr(clone_agent, "WANT", str(want))
    assert clone_agent.wanted() == "off"


def test_the_clone_learns_the_device_without_a_restart_and_without_hiding_stale_keys(lab):
    """push_passwd: the running clone's passwd names the device (no unit restarted); the marker of
    applied keys goes with it only when the clone's other keys are the current ones, else the next
    `fleet up` must still push them all."""
    import hashlib

    from ccrp_cli.robot import power
    from ccrp_cli.fleet import clone_view
    from ccrp_cli.providers.base import CloneState
    from ccrp_cli.render.bundles import clone_secrets

    v = lab.inventory.vpn
    lab.pki.issue_power("nao1", v.cert_days, v.crl_days)
    keys = [f for f in clone_secrets(clone_view(lab, lab.load_allocated(), "nao1"), lab.pki.credentials("nao1"))
            if f.name != "crl.pem"]

    class Clone:
        def __init__(self, stale: str | None):
            self.held = {f.dest: hashlib.sha256(f.content.encode()).hexdigest() for f in keys if f.name != stale}
            self.pushed = []

        def query(self):
            return {"nao1": SimpleRecord()}

        transport = property(lambda self: self)  # a fake clone is its own transport
        def exec(self, robot, argv, timeout=60):
            assert argv[0] == "sha256sum"
            return 0, "".join(f"{self.held[p]}  {p}\n" for p in argv[1:] if p in self.held)

        def push_files(self, robot, files, restart=()):
            assert restart == []
            self.pushed.append([f.name for f in files])

    class SimpleRecord:
        state = CloneState.RUNNING

    current = Clone(stale=None)
    power.push_passwd(lab, current, "nao1", lambda m: None)
    assert current.pushed == [["passwd", ".applied"]]
    behind = Clone(stale="server.crt")
    power.push_passwd(lab, behind, "nao1", lambda m: None)
    assert behind.pushed == [["passwd"]]


def test_a_real_robots_power_goes_through_its_clone_without_docker_here(lab, monkeypatch):
    """A cloud fleet's operator machine may have no Docker engine: a real robot's power command
    needs only its clone (the wish written there, the device's next report read there)."""
    from ccrp_cli.robot import power, simulated
    from ccrp_cli.errors import CcrpError

    def no_docker(*a, **k):
        raise CcrpError("cannot reach the Docker engine")

    monkeypatch.setattr(simulated, "Sims", no_docker)

    class Clone:  # the clone's power agent, and the device answering the wish at its next report
        report = {"relay": "on", "robot": "running"}

        transport = property(lambda self: self)  # a fake clone is its own transport
        def exec(self, robot, argv, timeout=60):
            if argv == ["cat", power.REPORT]:
                return 0, json.dumps({**self.report, "t": time.time()}) + "\n"
            if argv[:len(power.SET_STATE)] == power.SET_STATE:
                self.report = {"relay": argv[-1], "robot": "off" if argv[-1] == "off" else "running"}
                return 0, f"{int(time.time())}\n"
            return 0, '{"kill": ["SUCCESS: common name \'nao1\' found, 1 client(s) killed"]}\n'  # the dead session

    got = power.power(lab, "nao1", "off", provider=Clone(), timeout=5)
    assert (got["power"], got["robot_state"], got["device"]) == ("off", "off", "device")
    assert power.power(lab, "nao1", "status", provider=Clone())["power"] == "on"


# -- the agent's socket is systemd's (socket activation) -------------------------------------------------

# What systemd does before it execs a socket-activated service: the socket at fd 3, LISTEN_FDS, and
# LISTEN_PID set to the pid that then runs the service (exec keeps it); a test may set another.
AS_SYSTEMD = """
import os, sys
fd = int(sys.argv[1])
if fd != 3:
    os.dup2(fd, 3)
    os.close(fd)
os.environ.setdefault("LISTEN_PID", str(os.getpid()))
os.execv(sys.executable, [sys.executable, *sys.argv[2:]])
"""
# The clone's agent with its state files in the test's directory: argv want, report, power.json.
AGENT = f"""
import sys
sys.path.insert(0, {str(ROOT)!r})
from ccrp_cli.agent import power
power.WANT, power.REPORT = sys.argv[1:3]
sys.argv = ["power.py", sys.argv[3]]
power.main()
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_agent(tmp, port: int, fd3=None, env: dict | None = None) -> subprocess.Popen:
    """The agent for power.json's 127.0.0.1:port; given `fd3` (a socket, or any file), as systemd
    starts it, with LISTEN_FDS=1 unless `env` says otherwise."""
    (tmp / "power.json").write_text(json.dumps({"listen": "127.0.0.1", "port": port, "device": "127.0.0.1"}))
    agent = [sys.executable, "-c", AGENT, str(tmp / "want"), str(tmp / "report"), str(tmp / "power.json")]
    kw = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    if fd3 is None:
        return subprocess.Popen(agent, env={"PATH": os.environ["PATH"], **(env or {})}, **kw)
    return subprocess.Popen([sys.executable, "-c", AS_SYSTEMD, str(fd3.fileno()), *agent[1:]],
                            env={"PATH": os.environ["PATH"], "LISTEN_FDS": "1", **(env or {})},
                            pass_fds=(fd3.fileno(),), **kw)


def held_socket(port: int = 0) -> socket.socket:
    """A listening socket as ccrp-power.socket makes it; non-blocking, as a passed socket may be."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.setsockopt(socket.IPPROTO_IP, 15, 1)  # FreeBind=yes
    s.bind(("127.0.0.1", port))
    s.listen(8)
    s.setblocking(False)
    return s


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.communicate(timeout=30)


def test_the_agent_serves_on_the_socket_systemd_holds_and_binds_none_itself(tmp_path):
    """ccrp-power.socket holds the port, the agent gets it at fd 3 (LISTEN_FDS/LISTEN_PID, no
    python-systemd) and serves the device's reports on it. While it is held, across the agent's
    restarts too, nobody else binds it (the impersonation: bind the clone's VPN address first,
    IP_FREEBIND, and answer the device `relay: on`); a report sent while the agent is down waits in
    the socket's queue for the next agent."""
    device = runpy.run_path(str(ROOT / "templates/edge/ccrp-power-device"), run_name="ccrp_power_device")
    held = held_socket()
    port = held.getsockname()[1]
    cfg = {"CCRP_POWER_CLONE": "127.0.0.1", "CCRP_POWER_PORT": str(port)}
    (tmp_path / "want").write_text("off\n")
    agent = start_agent(tmp_path, port, held)
    try:
        started = agent.stdout.readline()
        assert started.startswith(f"ccrp-power: serving 127.0.0.1:{port} "), (started, agent.poll())
        assert device["exchange"](cfg, {"relay": "on", "robot": "running", "t": 1.0}) == "off"
        assert json.loads((tmp_path / "report").read_text())["device_t"] == 1.0
        stop(agent)
        # The agent is down (a restart): the port is still held, and still refused to anyone else.
        with socket.socket() as impostor:
            impostor.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            impostor.setsockopt(socket.IPPROTO_IP, 15, 1)
            with pytest.raises(OSError) as taken:
                impostor.bind(("127.0.0.1", port))
            assert taken.value.errno == 98  # EADDRINUSE
        waiting = socket.create_connection(("127.0.0.1", port), timeout=20)
        waiting.sendall(b'{"relay": "off", "robot": "off", "t": 2.0}\n')
        agent = start_agent(tmp_path, port, held)
        assert "ccrp-power: serving" in agent.stdout.readline()
        with waiting:
            assert json.loads(waiting.makefile().readline()) == {"relay": "off"}
        assert json.loads((tmp_path / "report").read_text())["device_t"] == 2.0
    finally:
        stop(agent)
        held.close()


@pytest.mark.parametrize("how", ["no variables", "another pid", "two sockets", "another port", "no socket at fd 3"])
def test_without_systemds_socket_the_agent_says_so_and_exits_once(tmp_path, how):
    """Run by hand, or by a unit without its socket: the agent binds nothing (a port it bound itself
    is the one any user could have bound first), says why in one line, and exits NO_SOCKET, which
    ccrp-power.service does not restart (test_the_power_units_give_the_agent_systemds_socket)."""
    from ccrp_cli.agent import power as clone_agent

    port, held, env = free_port(), None, {}
    if how == "another pid":  # LISTEN_PID names another process: the socket is not ours
        held, env = held_socket(port), {"LISTEN_PID": str(os.getpid())}
    elif how == "two sockets":
        held, env = held_socket(port), {"LISTEN_FDS": "2"}
    elif how == "another port":
        held = held_socket()  # what the unit holds is not what power.json names
    elif how == "no socket at fd 3":
        held = open(tmp_path / "plain", "w")  # noqa: SIM115
    proc = start_agent(tmp_path, port, held, env)
    try:
        out, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        stop(proc)
        pytest.fail(f"{how}: the agent kept running (it serves a port it bound itself)")
    finally:
        if held is not None:
            held.close()
    assert proc.returncode == clone_agent.NO_SOCKET == 78, (how, proc.returncode, err)
    assert "ccrp-power: no socket from systemd (" in err and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and out == ""


def test_the_power_units_give_the_agent_systemds_socket(lab):
    """The clone's user-data: ccrp-power.socket listens on the clone's VPN address (power.json's, and
    the firewall's) with FreeBind, from sockets.target, and is started alone before ccrp's services;
    the service requires it, never hits a start limit (that would close the socket) and does not
    restart on NO_SOCKET. No shell line: units and runcmd are argv built from constants."""
    from ccrp_cli.agent import power as clone_agent
    from ccrp_cli.fleet import clone_view
    from ccrp_cli.render import cloudinit
    from ccrp_cli.services.registry import boots

    view = clone_view(lab, lab.load_allocated(), "nao1")
    data = cloudinit.user_data_dict(view, boots())
    files = {f["path"]: f["content"] for f in data["write_files"]}

    def unit(path: str) -> dict[str, list[str]]:
        """Each `Key=` of a unit file -> its values in order (comments and sections dropped)."""
        keys: dict[str, list[str]] = {}
        for line in files[path].splitlines():
            if "=" in line and not line.startswith(("#", ";", "[")):
                key, value = line.split("=", 1)
                keys.setdefault(key, []).append(value)
        return keys

    sock, service = unit("/etc/systemd/system/ccrp-power.socket"), unit("/etc/systemd/system/ccrp-power.service")
    ip = str(view.addr.clone_vpn_ip)
    assert json.loads(files["/etc/ccrp/power.json"])["listen"] == ip
    assert sock["ListenStream"] == [f"{ip}:11400"] and sock["FreeBind"] == ["yes"]
    assert sock["WantedBy"] == ["sockets.target"] and "DefaultDependencies" not in sock  # Before=sockets.target
    assert not any(k.startswith("Exec") or k == "Accept" for k in sock)  # Accept=no: one agent takes the socket
    assert f"-d {ip} -p tcp --dport 11400 -j ACCEPT" in files["/etc/ccrp/firewall.rules"]
    assert service["Requires"] == ["ccrp-power.socket"] and "ccrp-power.socket" in " ".join(service["After"]).split()
    assert service["StartLimitIntervalSec"] == ["0"] and "StartLimitBurst" not in service
    assert service["RestartPreventExitStatus"] == [str(clone_agent.NO_SOCKET)] and service["Restart"] == ["always"]
    assert service["ExecStart"] == ["/usr/bin/python3 /usr/local/lib/ccrp/power.py /etc/ccrp/power.json"]
    assert service["User"] == ["ccrp-power"] and "Sockets" not in service  # the socket of its own name
    runcmd = data["runcmd"]
    assert all(isinstance(c, list) and "sh" not in c[:1] for c in runcmd), runcmd
    starts = [i for i, c in enumerate(runcmd) if c[:2] == ["systemctl", "start"]]
    assert runcmd[starts[0]] == ["systemctl", "start", "ccrp-power.socket"]
    assert len(starts) == 2 and "ccrp-power.service" in runcmd[starts[1]] and starts[0] < starts[1]
