"""With --json, a failing command prints one error envelope on stdout ({"error": {"code", "message",
"hint"}}, code = the exit code), besides its one line on stderr; exit codes are unchanged."""

from __future__ import annotations

import json

import pytest

from ccrp_cli.cli.output import wants_json
from ccrp_cli.errors import BAD_INPUT, INTERRUPTED, CcrpError, InputError, failure, one_line
from tests.conftest import LAB


def envelope(proc) -> dict:
    assert "Traceback" not in proc.stderr, proc.stderr
    data = json.loads(proc.stdout)
    assert set(data) == {"error"} and set(data["error"]) == {"code", "message", "hint"}, data
    assert data["error"]["code"] == proc.returncode
    # The same failure as the line on stderr, which stays as it was.
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("ccrp: error: ") and data["error"]["message"] in line
    return data["error"]


@pytest.mark.parametrize("args, said", [
    (("fleet", "validate", "-i", "does-not-exist.yaml"), "does-not-exist.yaml"),  # no such inventory
    (("fleet", "scale", "many", "-i", str(LAB)), "'size'"),  # an argument the parser refuses
    (("clone", "create", "-i", str(LAB), "--robot", "nao9"), "nao9"),  # not a robot of the fleet
    (("vpn", "issue-cert", "-i", str(LAB)), "--robot"),  # a missing option
])
def test_a_command_refusing_its_input_with_json_prints_the_envelope_exit_2(ccrp, ccrp_home, args, said):
    proc = ccrp(*args, "--json")
    assert proc.returncode == BAD_INPUT, proc.stderr
    error = envelope(proc)
    assert said in error["message"]
    assert not ccrp_home.exists() or not any(ccrp_home.rglob("state.json"))  # nothing changed


def test_an_operation_failing_with_json_keeps_its_exit_code_and_hint(ccrp):
    proc = ccrp("vpn", "list", "-i", str(LAB), "--json")  # no PKI yet
    assert proc.returncode == 1
    error = envelope(proc)
    assert "vpn init" in error["hint"]


def test_without_json_stdout_stays_empty(ccrp):
    proc = ccrp("fleet", "validate", "-i", "does-not-exist.yaml")
    assert proc.returncode == BAD_INPUT and proc.stdout == "" and proc.stderr.startswith("ccrp: error: ")


def test_json_is_asked_by_ccrps_own_arguments_only():
    assert wants_json(["status", "--json"]) and wants_json(["fleet", "up", "--json", "-i", "x.yaml"])
    assert not wants_json(["status"])
    # After `--`, the arguments are a command's run on the clone (`ccrp clone exec`).
    assert not wants_json(["clone", "exec", "--robot", "nao1", "--", "tool", "--json"])
    assert wants_json(["clone", "exec", "--json", "--robot", "nao1", "--", "tool"])


def test_every_failure_is_translated_in_one_place():
    refused = InputError("bad   name\n'x'", hint="use  another")
    assert failure(refused) is refused
    assert refused.envelope() == {"error": {"code": 2, "message": "bad name 'x'", "hint": "use another"}}
    assert CcrpError("boom").envelope() == {"error": {"code": 1, "message": "boom", "hint": None}}
    assert failure(KeyboardInterrupt()).code == INTERRUPTED
    bug = failure(ValueError("no\nsuch thing"))
    assert bug.code == 1 and bug.one_line() == "ValueError: no such thing"
    assert one_line(ValueError("x" * 500), 300) == ("ValueError: " + "x" * 500)[:299] + "…"
    assert one_line(refused) == "bad name 'x' (hint: use another)"
