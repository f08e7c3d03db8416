"""`ccrp logs` across the fleet (docs/workloads.md, Logs): the robots selected as other fleet
commands select them, lines merged by the journal's time with a robot/node prefix, --json records,
-n per node, --follow with one reader per clone, a clone that cannot be read reported once, and
--since that matches nothing never making --follow print the history (the cursor bug)."""

from __future__ import annotations

import json

import pytest
import yaml

from ccrp_cli import providers
from ccrp_cli.cli import logs as cli_logs
from ccrp_cli.errors import CcrpError
from ccrp_cli.ops.logs import merge, node_of
from tests.conftest import LAB
from tests.inprocess_cli import run_ccrp_inprocess

NOW = 1_800_000_000_000_000  # the clones' clock, in journald's microseconds
OLD = NOW - 3600 * 10**6  # an hour before: outside --since 10m


def entry(cursor: str, micros: int, unit: str, message: str) -> dict:
    return {"__CURSOR": cursor, "__REALTIME_TIMESTAMP": str(micros), "_SYSTEMD_UNIT": f"ccrp-run-{unit}.service",
            "_PID": "40", "MESSAGE": message}


class Fleet:
    """Clones (their own transport) each with a journal that answers journalctl as the real one
    does for what ccrp asks: --unit filters, --since -Ns, --after-cursor, then the last (or, after
    a cursor, the first) --lines. `stopped` clones fail as a stopped container does; after
    `rounds` polls of any clone, Ctrl-C."""

    def __init__(self, journals: dict[str, list[dict]], stopped=(), interrupt_after: int | None = None) -> None:
        self.journals, self.stopped, self.interrupt_after = journals, set(stopped), interrupt_after
        self.argvs: list[tuple[str, list[str]]] = []
        self.polls = 0
        self.on_poll = lambda n: None  # what happens on the clones before the n-th poll

    transport = property(lambda self: self)

    def exec(self, robot, argv, timeout=60):
        self.argvs.append((robot, argv))
        if "--after-cursor" in argv:
            self.polls += 1
            if self.interrupt_after is not None and self.polls > self.interrupt_after:
                raise KeyboardInterrupt  # how an operator ends --follow
            self.on_poll(self.polls)
        if robot in self.stopped:
            raise CcrpError(f"clone of robot {robot!r} is not running")
        units = {argv[i + 1] for i, a in enumerate(argv) if a == "--unit"}
        got = [e for e in self.journals[robot] if e["_SYSTEMD_UNIT"] in units]
        if "--since" in argv:
            got = [e for e in got if int(e["__REALTIME_TIMESTAMP"]) >= NOW + int(argv[argv.index("--since") + 1][:-1]) * 10**6]
        lines = int(argv[argv.index("--lines") + 1])
        if "--after-cursor" in argv:
            cursors = [e["__CURSOR"] for e in got]
            got = got[cursors.index(argv[argv.index("--after-cursor") + 1]) + 1:][:lines]
        else:
            got = got[-lines:]
        return 0, "".join(json.dumps(e) + "\n" for e in got)

    def reads(self) -> list[tuple[str, list[str]]]:
        return [(robot, argv) for robot, argv in self.argvs if "--after-cursor" not in argv]


@pytest.fixture
def inv(tmp_path):
    """inventories/lab.yaml with nodes: every robot runs mapper, the nao ones faces, turtlebot1 planner."""
    data = yaml.safe_load(LAB.read_text())
    data["software"] = {"run": [{"name": "mapper", "command": ["m"]}]}
    data["types"] = {"nao": {"software": {"run": [{"name": "faces", "command": ["f"]}]}}}
    for r in data["robots"]:
        if r["name"] == "turtlebot1":
            r["software"] = {"run": [{"name": "planner", "command": ["p"]}]}
    path = tmp_path / "inventory.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def ccrp(tmp_path, monkeypatch, clones: Fleet, inv, *args):
    monkeypatch.setattr(providers, "get_provider", lambda inventory: clones)
    monkeypatch.setattr(cli_logs.time, "sleep", lambda s: None)
    return run_ccrp_inprocess("logs", "-i", str(inv), *args, home=tmp_path / "home")


def journals() -> dict[str, list[dict]]:
    return {
        "nao1": [entry("a1", NOW - 5000, "mapper", "nao1 mapper up"), entry("a2", NOW - 3000, "faces", "nao1 faces up"),
                 entry("a3", NOW - 1000, "mapper", "nao1 map 1")],
        "nao2": [entry("b1", NOW - 4000, "mapper", "nao2 mapper up"), entry("b2", NOW - 1000, "mapper", "nao2 map 1")],
        "turtlebot1": [entry("t1", NOW - 2000, "planner", "planning")],
    }


def test_merge_orders_by_time_and_keeps_ties_in_robot_then_journal_order():
    t = "2027-01-15T08:00:00.00000{}+00:00".format
    nao1 = [{"robot": "nao1", "node": "mapper", "time": t(1), "message": "a"},
            {"robot": "nao1", "node": "faces", "time": t(3), "message": "b"},
            {"robot": "nao1", "node": "mapper", "time": t(3), "message": "c"}]
    nao2 = [{"robot": "nao2", "node": "mapper", "time": t(2), "message": "d"},
            {"robot": "nao2", "node": "mapper", "time": t(3), "message": "e"}]
    assert [r["message"] for r in merge([nao1, nao2])] == ["a", "d", "b", "c", "e"]
    assert [r["message"] for r in merge([nao2, nao1])] == ["a", "d", "e", "b", "c"]
    assert node_of("ccrp-run-mapper.service") == "mapper" and node_of("ccrp-relay.service") == "relay"
    assert node_of("init.scope") == "init.scope"


def test_all_merges_every_robots_nodes_by_time_with_padded_prefixes(tmp_path, monkeypatch, inv):
    clones = Fleet(journals())
    code, out, err = ccrp(tmp_path, monkeypatch, clones, inv, "--all")
    assert code == 0, err
    assert out.splitlines() == [
        "nao1/mapper        | 2027-01-15T07:59:59.995 nao1 mapper up",
        "nao2/mapper        | 2027-01-15T07:59:59.996 nao2 mapper up",
        "nao1/faces         | 2027-01-15T07:59:59.997 nao1 faces up",
        "turtlebot1/planner | 2027-01-15T07:59:59.998 planning",
        "nao1/mapper        | 2027-01-15T07:59:59.999 nao1 map 1",  # a tie: in the order the robots are named
        "nao2/mapper        | 2027-01-15T07:59:59.999 nao2 map 1",
    ], out
    lines = out.splitlines()
    assert {x.index(" | ") for x in lines} == {len("turtlebot1/planner")}, out  # one width, as docker compose
    # -n: each node's last lines, one read per node (a chatty node does not crowd out a quiet one).
    assert sorted((robot, argv[argv.index("--unit") + 1], argv[-1]) for robot, argv in clones.reads()) == [
        ("nao1", "ccrp-run-faces.service", "100"), ("nao1", "ccrp-run-mapper.service", "100"),
        ("nao2", "ccrp-run-faces.service", "100"), ("nao2", "ccrp-run-mapper.service", "100"),
        ("turtlebot1", "ccrp-run-mapper.service", "100"), ("turtlebot1", "ccrp-run-planner.service", "100")]
    code, out, err = ccrp(tmp_path, monkeypatch, Fleet(journals()), inv, "--all", "-n", "1")
    assert [x.split(" | ")[0].strip() for x in out.splitlines()] == ["nao1/faces", "turtlebot1/planner", "nao1/mapper", "nao2/mapper"]


def test_json_is_one_record_per_line_with_robot_node_and_utc_time(tmp_path, monkeypatch, inv):
    code, out, err = ccrp(tmp_path, monkeypatch, Fleet(journals()), inv, "--type", "nao", "mapper", "--json")
    assert code == 0, err
    records = [json.loads(x) for x in out.splitlines()]
    assert records[0] == {"robot": "nao1", "node": "mapper", "time": "2027-01-15T07:59:59.995000+00:00",
                          "message": "nao1 mapper up"}
    assert [(r["robot"], r["message"]) for r in records] == [
        ("nao1", "nao1 mapper up"), ("nao2", "nao2 mapper up"), ("nao1", "nao1 map 1"), ("nao2", "nao2 map 1")]
    import datetime as dt

    times = [dt.datetime.fromisoformat(r["time"]) for r in records]
    assert all(t.utcoffset() == dt.timedelta(0) for t in times)
    assert [int(t.timestamp() * 10**6) for t in times[:2]] == [NOW - 5000, NOW - 4000]  # to the microsecond


def test_a_robot_or_type_that_does_not_exist_is_one_line_and_nothing_is_read(tmp_path, monkeypatch, inv):
    for args, says in ((["--robot", "nao1,ghost"], "robot 'ghost' is not in fleet"),
                       (["--type", "drone"], "no robot of fleet"),
                       ([], "name the robots to read"),
                       (["--robot", "nao1", "--all"], "name the robots to read"),
                       (["--robot", ","], "--robot names no robot"),
                       (["--all", "ghostnode"], "neither a node")):
        clones = Fleet(journals())
        code, out, err = ccrp(tmp_path, monkeypatch, clones, inv, *args)
        assert code == 2 and len(err.splitlines()) == 1 and says in err, (args, err)
        assert clones.argvs == [], args


def test_a_node_some_robots_lack_reads_those_that_have_it(tmp_path, monkeypatch, inv):
    clones = Fleet(journals())
    code, out, err = ccrp(tmp_path, monkeypatch, clones, inv, "--all", "faces")
    assert code == 0 and {robot for robot, _ in clones.argvs} == {"nao1", "nao2"}, err
    assert out.splitlines() == ["nao1/faces | 2027-01-15T07:59:59.997 nao1 faces up"], out


def test_since_that_matches_nothing_then_follow_prints_only_new_lines(tmp_path, monkeypatch, inv):
    """The cursor bug: the first read (--since 10m) found nothing, so there was no cursor, and the
    first poll asked for the last lines: the hour-old history came out as if new."""
    clones = Fleet({"nao1": [entry("a1", OLD, "mapper", "old 1"), entry("a2", OLD + 1, "mapper", "old 2")]},
                   interrupt_after=3)
    clones.on_poll = lambda n: n == 2 and clones.journals["nao1"].append(entry("a3", NOW + 10**6, "mapper", "new 1"))
    code, out, err = ccrp(tmp_path, monkeypatch, clones, inv, "--robot", "nao1", "mapper", "--since", "10m", "-f")
    assert code == 0, err
    assert "old" not in out, out
    assert [x.rsplit(" ", 2)[-2:] for x in out.splitlines()] == [["new", "1"]], out
    assert not err, err


def test_follow_reads_every_clone_and_goes_on_when_one_cannot_be_read(tmp_path, monkeypatch, inv):
    clones = Fleet(journals(), stopped={"turtlebot1"}, interrupt_after=6)

    def on_poll(n: int) -> None:
        if n == 3:
            clones.journals["nao2"].append(entry("b3", NOW + 10**6, "faces", "nao2 saw a face"))
        if n == 5:
            clones.journals["nao1"].append(entry("a4", NOW + 2 * 10**6, "mapper", "nao1 map 2"))

    clones.on_poll = on_poll
    code, out, err = ccrp(tmp_path, monkeypatch, clones, inv, "--all", "-n", "1", "-f")
    assert code == 0, err
    # The first read: nao1's and nao2's last line of each node; then each new line once, as it comes.
    assert [x.split(" | ")[0].strip() for x in out.splitlines()] == [
        "nao1/faces", "nao1/mapper", "nao2/mapper", "nao2/faces", "nao1/mapper"], out
    assert out.splitlines()[-2].endswith("nao2 saw a face") and out.splitlines()[-1].endswith("nao1 map 2")
    # The stopped clone: said once (it was asked again each round), the others went on.
    assert len(err.splitlines()) == 1 and "robot 'turtlebot1'" in err and "following the others" in err, err
    assert sum(robot == "turtlebot1" for robot, _ in clones.argvs) > 2


def test_without_follow_a_clone_that_cannot_be_read_is_said_and_the_exit_code_is_3(tmp_path, monkeypatch, inv):
    code, out, err = ccrp(tmp_path, monkeypatch, Fleet(journals(), stopped={"turtlebot1"}), inv, "--all")
    assert code == 3 and "nao1 map 1" in out and len(err.splitlines()) == 1 and "'turtlebot1'" in err, err
    code, out, err = ccrp(tmp_path, monkeypatch, Fleet(journals(), stopped={"turtlebot1"}), inv, "--robot", "turtlebot1")
    assert code == 1 and not out and "not running" in err, err


def test_prefixes_are_coloured_on_a_terminal_only(monkeypatch, capsys):
    from ccrp_cli.ops.logs import Reader

    readers = [Reader("nao1", ["ccrp-run-mapper.service"]), Reader("nao2", ["ccrp-run-mapper.service"])]
    records = [{"robot": "nao1", "node": "mapper", "time": "2027-01-15T08:00:00.000000+00:00", "message": "\x1b[2Jhi"},
               {"robot": "nao2", "node": "mapper", "time": "2027-01-15T08:00:00.000000+00:00", "message": "ho"}]
    cli_logs.Lines(readers).show(records)
    assert capsys.readouterr().out == ("nao1/mapper | 2027-01-15T08:00:00.000 \\x1b[2Jhi\n"
                                       "nao2/mapper | 2027-01-15T08:00:00.000 ho\n")
    monkeypatch.setattr(cli_logs.sys.stdout, "isatty", lambda: True)
    monkeypatch.delenv("NO_COLOR", raising=False)
    cli_logs.Lines(readers).show(records)
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "\x1b[36mnao1/mapper\x1b[0m | 2027-01-15T08:00:00.000 \\x1b[2Jhi"  # the node's escape: escaped
    assert out[1].startswith("\x1b[33mnao2/mapper\x1b[0m | ")
    monkeypatch.setenv("NO_COLOR", "1")
    cli_logs.Lines(readers).show(records)
    assert "\x1b[3" not in capsys.readouterr().out
