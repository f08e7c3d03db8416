"""A clone's text on the operator's terminal (docs/security.md): a node's journal, a failed step's
output and a status cell come out with their control characters escaped, a node cannot label its
lines as another unit's, and one exec's answer is capped, whatever the clone sends."""

from __future__ import annotations

import json
import re
from types import SimpleNamespace

import pytest

from ccrp_cli.errors import CcrpError, printable
from ccrp_cli.ops import logs as ops_logs
from ccrp_cli.services.workloads import read_journal
from ccrp_cli.transport import EXEC_OUTPUT_MAX
from tests.conftest import LAB
from tests.inprocess_cli import run_ccrp_inprocess
from tests.unit.test_deploy import Clones as DeployClones
from tests.unit.test_deploy import built, change_workspace, fleet  # noqa: F401 - fixtures

# What a node can log: OSC 52 (writes the operator's clipboard), a screen clear, C1 CSI (U+009B, an
# escape to an 8-bit terminal), DEL, and a newline and a CR that would forge a line of ccrp's own.
EVIL = "hi\x1b]52;c;cm0gLXJmIH4K\x07 \x1b[2J\u009b31m\x7f\nccrp: deployed\rX\ttab"
# Control characters a terminal acts on: C0 but tab and the newline ending each line, DEL, C1.
RAW = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f]")


def test_printable_escapes_every_control_character_and_keeps_the_text():
    assert printable(EVIL) == "hi\\x1b]52;c;cm0gLXJmIH4K\\x07 \\x1b[2J\\x9b31m\\x7f\\nccrp: deployed\\rX\ttab"
    assert printable("é ü ✓ C:\\path \\x1b") == "é ü ✓ C:\\path \\x1b"  # text, and a backslash, as they are
    assert printable(printable(EVIL)) == printable(EVIL)  # escaping twice changes nothing
    # A right-to-left override makes "ok\u202e...gnilaf" read as something else; a zero-width space hides.
    assert printable("ok\u202egnilaf\u2066x\u2069\u200by\ufeff") == "ok\\u202egnilaf\\u2066x\\u2069\\u200by\\ufeff"
    assert not RAW.search(printable("".join(map(chr, range(0x100)))))
    assert CcrpError(f"deploy step stage failed: {EVIL}", hint="\x1b[2J").one_line() == (
        "deploy step stage failed: hi\\x1b]52;c;cm0gLXJmIH4K\\x07 \\x1b[2J\\x9b31m\\x7f ccrp: deployed X tab"  # whitespace: one space
        " (hint: \\x1b[2J)")


class Journal:
    """A clone (its own transport) whose journal holds `entries`; records each journalctl argv."""

    def __init__(self, entries: list[dict], stop_after: int | None = None) -> None:
        self.entries, self.stop_after, self.argvs = entries, stop_after, []

    transport = property(lambda self: self)

    def exec(self, robot, argv, timeout=60):
        self.argvs.append(argv)
        if self.stop_after is not None and len(self.argvs) > self.stop_after:
            raise KeyboardInterrupt  # how an operator ends --follow
        return 0, "".join(json.dumps(e) + "\n" for e in self.entries)


def entry(n: int, message, **fields) -> dict:
    return {"__CURSOR": f"c{n}", "__REALTIME_TIMESTAMP": str(1700000000000000 + n * 1000),
            "_SYSTEMD_UNIT": "ccrp-relay.service", "_PID": "812", "MESSAGE": message, **fields}


def test_logs_print_a_nodes_escape_sequences_escaped_and_json_exact(tmp_path, monkeypatch):
    from ccrp_cli import providers

    clone = Journal([entry(1, EVIL), entry(2, list(b"bytes \x1b[2J \x9b \xff")), entry(3, "fine")])
    monkeypatch.setattr(providers, "get_provider", lambda inventory: clone)
    code, out, err = run_ccrp_inprocess("logs", "-i", str(LAB), "--robot", "nao1", "relay", home=tmp_path / "home")
    assert code == 0, err
    lines = out.splitlines()
    assert len(lines) == 3 and not RAW.search(out), out  # one line per entry, nothing a terminal acts on
    assert all(x.startswith("nao1/relay | 2023-11-14T22:13:20.00") for x in lines), lines
    assert lines[0].endswith(" hi\\x1b]52;c;cm0gLXJmIH4K\\x07 \\x1b[2J\\x9b31m\\x7f\\nccrp: deployed\\rX\ttab")
    assert lines[1].endswith(" bytes \\x1b[2J \ufffd \ufffd")  # not UTF-8: journald's list of bytes
    assert lines[2].endswith(" fine")
    # --json: the exact text, JSON-escaped (no raw control character either).
    code, out, err = run_ccrp_inprocess("logs", "-i", str(LAB), "--robot", "nao1", "relay", "--json", home=tmp_path / "home")
    assert code == 0 and not RAW.search(out), err
    assert [json.loads(x)["message"] for x in out.splitlines()][0] == EVIL


def test_a_nodes_unit_field_does_not_label_its_lines():
    clone = Journal([
        # mapper's node sets UNIT (any sender may) to pass its lines off as the relay's.
        entry(1, "relay: key rotated", _SYSTEMD_UNIT="ccrp-run-mapper.service", UNIT="ccrp-relay.service", _PID="4242"),
        # systemd's own line about the unit: its sender is init.scope, UNIT names the unit.
        entry(2, "Started ccrp-run-mapper.service.", _SYSTEMD_UNIT="init.scope", UNIT="ccrp-run-mapper.service", _PID="1"),
        entry(3, "no unit at all", _SYSTEMD_UNIT=None, UNIT="ccrp-relay.service", _PID="77"),
    ])
    entries, _ = read_journal(clone, "nao1", ["ccrp-run-mapper.service"], 50)
    assert [e["unit"] for e in entries] == ["ccrp-run-mapper.service", "ccrp-run-mapper.service", ""]
    assert "_PID" in clone.argvs[0][clone.argvs[0].index("--output-fields") + 1].split(",")


def test_logs_follow_reads_bounded_pages(tmp_path, monkeypatch):
    from ccrp_cli import providers
    from ccrp_cli.cli import logs

    clone = Journal([entry(n, f"line {n}") for n in range(3)], stop_after=3)
    sleeps = []
    monkeypatch.setattr(providers, "get_provider", lambda inventory: clone)
    monkeypatch.setattr(logs.time, "sleep", sleeps.append)
    code, out, err = run_ccrp_inprocess("logs", "-i", str(LAB), "--robot", "nao1", "relay", "-f", "-n", "20",
                                        home=tmp_path / "home")
    assert code == 0 and len(clone.argvs) == 4 and len(sleeps) == 2, err
    assert clone.argvs[0][-2:] == ["--lines", "1"]  # the journal's tail: where the polls read on from
    assert clone.argvs[1][-2:] == ["--lines", "20"]
    assert out.count("line 1") == 1, out  # the first poll sees what the first read showed: shown once
    for argv in clone.argvs[2:]:  # each poll: at most FOLLOW_PAGE entries after the last cursor
        assert argv[-4:] == ["--after-cursor", "c2", "--lines", str(ops_logs.FOLLOW_PAGE)], argv
    # A full page: more is waiting, read at once (a node that floods costs lag, not memory).
    clone.argvs.clear(), sleeps.clear()
    monkeypatch.setattr(ops_logs, "FOLLOW_PAGE", 3)
    run_ccrp_inprocess("logs", "-i", str(LAB), "--robot", "nao1", "relay", "-f", home=tmp_path / "home")
    assert len(clone.argvs) == 4 and len(sleeps) == 1 and clone.argvs[2][-1] == "3", clone.argvs


class EvilJournal(DeployClones):
    """deploy's directory clones, whose failing node logged escape sequences."""

    def exec(self, robot, argv, timeout=60):
        if argv[0] == "journalctl":
            self.execs.append((robot, argv))
            return 0, json.dumps(entry(1, EVIL, _SYSTEMD_UNIT=argv[-3])) + "\n"
        return super().exec(robot, argv, timeout)


def test_deploys_failure_line_shows_the_nodes_log_escaped(fleet, built, capsys):  # noqa: F811 - fixtures
    from ccrp_cli.cli import output
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops import deploy

    fleet, clones, _ = fleet
    evil = EvilJournal(clones.root / "evil", clones.robots)
    evil.root = clones.root  # the same clone directories
    change_workspace(fleet)
    evil.states["ccrp-run-mapper.service"] = ("activating", "auto-restart", 2)
    [result] = deploy.deploy(Fleet.open(fleet.path), evil, output.info, robot="nao1")
    assert result.action == "failed" and EVIL in result.detail  # the record keeps the clone's text
    output.results([result], as_json=False)
    out, err = capsys.readouterr()
    for shown in (out, err):
        assert not RAW.search(shown) and "\\x1b]52;c;cm0gLXJmIH4K\\x07" in shown and "\\nccrp: deployed" in shown, shown
    output.results([result], as_json=True)
    out, _ = capsys.readouterr()
    assert not RAW.search(out) and EVIL in json.loads(out)[0]["detail"]


class EvilStatus:
    """Clones whose health reports name nodes with escape sequences (nao1), or whose transport
    failed with the clone's bytes in its message (nao2)."""

    max_parallel = 3
    transport = property(lambda self: self)

    def query(self):
        from ccrp_cli.providers.base import CloneRecord, CloneState

        return {r: CloneRecord(robot=r, provider_id=r, state=CloneState.RUNNING, status="running")
                for r in ("nao1", "nao2", "turtlebot1")}

    def stop_note(self, robot):
        return None

    def timeout_scale(self, robot):
        return 1

    def exec(self, robot, argv, timeout=60):
        if robot == "nao2":
            raise CcrpError(f"`health` on nao2 failed: {EVIL}")
        nodes = {"/talker\x1b]8;;http://evil/\x07[link=http://evil]x[/link]": f"http://{robot}:4000/"}
        return 0, json.dumps({"vpn": {"up": True, "clients": [{"cn": robot, "real_address": "198.51.100.7:1194"}]},
                              "master": {"reachable": True, "nodes": nodes},
                              "nodes": [{"name": "mapper", "state": "failed\x1b[2J", "sub": "x", "restarts": 1}]})


def test_status_cells_and_alerts_show_a_clones_text_escaped(lab_up, ccrp_home, monkeypatch):
    from ccrp_cli import providers

    monkeypatch.setattr(providers, "get_provider", lambda inventory: EvilStatus())
    code, out, err = run_ccrp_inprocess("status", "-i", str(LAB), home=ccrp_home)
    assert code == 0, err
    assert not RAW.search(out + err), out
    # The node's name as it is, markup-looking brackets included: neither escape nor rich markup acts.
    assert "/talker\\x1b]8;;http://evil/\\x07[link=http://evil]x[/link]" in out
    assert "mapper failed\\x1b[2J (1 restarts)" in out, out  # a node's state, as systemd on the clone said
    code, out, _ = run_ccrp_inprocess("status", "-i", str(LAB), "--json", home=ccrp_home)
    rows = {r["robot"]: r for r in json.loads(out)}
    assert code == 0 and not RAW.search(out)
    assert rows["nao1"]["robot_nodes"] == ["/talker\x1b]8;;http://evil/\x07[link=http://evil]x[/link]"]  # exact
    assert "\\x1b]52;c;cm0gLXJmIH4K\\x07" in rows["nao2"]["unreachable"]  # an error's line: escaped as on stderr


# -- one exec's answer is capped ------------------------------------------------------------------

class Flood:
    """A channel, or an engine exec stream, that never stops sending."""

    def __init__(self) -> None:
        self.sent, self.closed = 0, False

    def __iter__(self):
        return self

    def __next__(self) -> bytes:
        return self.recv(1 << 16)

    def recv(self, n: int) -> bytes:
        self.sent += n
        return b"y\n" * (n // 2)

    def close(self) -> None:
        self.closed = True

    # paramiko's Channel, as SshTransport.exec uses it
    def set_combine_stderr(self, on):
        pass

    def exec_command(self, command):
        pass

    def settimeout(self, t):
        pass


def test_an_ssh_exec_stops_reading_a_clone_that_floods_it():
    from ccrp_cli.transport.ssh import SshTransport

    flood = Flood()
    session = SimpleNamespace(is_active=lambda: True, open_session=lambda timeout: flood)
    ssh = SshTransport("192.0.2.5", "ccrp", "/nonexistent/key")
    ssh._client = SimpleNamespace(get_transport=lambda: session, close=lambda: None)
    with pytest.raises(CcrpError, match=r"wrote over 96 MiB; ccrp stopped reading it"):
        ssh.exec(["journalctl", "-f"], timeout=60)
    assert flood.closed and EXEC_OUTPUT_MAX < flood.sent <= EXEC_OUTPUT_MAX + (1 << 16)


def test_an_engine_exec_stops_reading_a_container_that_floods_it():
    from ccrp_cli.providers.base import LABEL_FLEET, LABEL_ROBOT, LABEL_ROLE
    from ccrp_cli.providers.docker.client import DockerHost

    flood = Flood()
    container = SimpleNamespace(id="c1", status="running", labels={LABEL_FLEET: "lab", LABEL_ROLE: "clone", LABEL_ROBOT: "nao1"})
    api = SimpleNamespace(exec_create=lambda cid, argv: {"Id": "e1"}, exec_start=lambda run, stream: flood,
                          exec_inspect=lambda run: {"Running": False, "ExitCode": 0})
    host = DockerHost.__new__(DockerHost)  # no engine: the client is a fake
    host.fleet, host.NotFound = "lab", LookupError
    host.engine = SimpleNamespace(api=api, containers=SimpleNamespace(get=lambda name: container))
    with pytest.raises(CcrpError, match=r"wrote over 96 MiB"):
        host.exec("nao1", ["cat", "/dev/zero"])
    assert flood.closed and EXEC_OUTPUT_MAX < flood.sent <= EXEC_OUTPUT_MAX + (1 << 16)
    # A bounded answer comes back whole, with its exit status.
    api.exec_start = lambda run, stream: Chunks([b"a\n", b"\x1b[2Jb\n"])
    inspected = iter([{"Running": True, "ExitCode": None}, {"Running": False, "ExitCode": 3}])
    api.exec_inspect = lambda run: next(inspected)  # the engine records the exit status a moment later
    assert host.exec("nao1", ["cat", "x"]) == (3, "a\n\x1b[2Jb\n")  # the exact text: printing escapes it


class Chunks(list):
    def close(self) -> None:
        pass


def test_the_dashboards_log_lines_escape_a_requests_path():
    import logging

    from ccrp_cli.dashboard.server import _Printable

    record = logging.makeLogRecord({"msg": '%s "GET %s" refused', "args": ("10.0.0.9", "/\x1b]52;c;eA==\x07\n200 OK")})
    assert _Printable("ccrp: dashboard: %(message)s").format(record) == \
        'ccrp: dashboard: 10.0.0.9 "GET /\\x1b]52;c;eA==\\x07\\n200 OK" refused'


def test_clone_exec_output_is_exact_in_a_pipe_and_escaped_on_a_terminal(capsys, monkeypatch):
    import sys

    from ccrp_cli.cli import output

    text = f"line 1\n{EVIL}\n"
    output.command_output(text)
    assert capsys.readouterr().out == text  # `ccrp clone exec -- cat f > f.copy` gets what the clone sent
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True)
    output.command_output(text)
    out = capsys.readouterr().out
    assert out == "line 1\nhi\\x1b]52;c;cm0gLXJmIH4K\\x07 \\x1b[2J\\x9b31m\\x7f\nccrp: deployed\\rX\ttab\n"  # lines kept


def test_the_cap_is_above_the_largest_answer_ccrp_asks_for():
    from ccrp_cli.robot.camera import MAX_JPEG
    from ccrp_cli.services.knowledge import MAX_ITEM

    def b64(n: int) -> int:
        return 4 * ((n + 2) // 3)

    # `knowledge merge` reads an item as one line of base64; a camera frame comes in JSON, as base64.
    assert b64(MAX_ITEM) + 1 < EXEC_OUTPUT_MAX and b64(MAX_JPEG) + 4096 < EXEC_OUTPUT_MAX
