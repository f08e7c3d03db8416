"""A no-op `fleet up` asks each running clone once (issue 12): the probe's answer as ensure_clone
reads it, and the relay configs that a run already knows are current."""

from __future__ import annotations

import hashlib

from ccrp_cli.ops import clones, reconcile
from ccrp_cli.ops.clones import StateWriter, probe
from ccrp_cli.services.sharing import relay_config_file
from ccrp_cli.providers.base import CloneRecord, CloneState
from ccrp_cli.render.files import BundleFile
from ccrp_cli.services.sharing import relay_config

RESULT = '{\n "v1": {\n  "datasource": "DataSourceNoCloud",\n  "errors": []\n }\n}\n'


class Clone:
    """A provider whose clone answers every command with one canned reply; records the commands."""

    max_parallel = 4

    def __init__(self, rc: int, out: str, stopped: tuple[str, ...] = ()) -> None:
        self.rc, self.out, self.calls, self.pushed, self.stopped = rc, out, [], [], stopped
        self.robots: list[str] = []

    def query(self):
        return {r: CloneRecord(robot=r, provider_id=r, status="x",
                               state=CloneState.STOPPED if r in self.stopped else CloneState.RUNNING)
                for r in self.robots}

    transport = property(lambda self: self)  # a fake clone is its own transport
    def exec(self, robot, argv, timeout=60):
        self.calls.append(argv)
        return self.rc, self.out

    def push_files(self, robot, files, restart=()):
        self.pushed.append((robot, [f.name for f in files]))


def reply(result: str, digests: dict[str, str], vpn: str = "yes", master: str = "yes") -> str:
    lines = "".join(f"{d}  {path}\n" for path, d in digests.items())
    return f"== result\n{result}\n== digests\n{lines}== serving vpn={vpn} master={master}\n"


def test_probe_reads_result_digests_and_serving_from_one_command():
    files = [BundleFile("a", "x", 0o600, "/k/a"), BundleFile("b", "y", 0o600, "/k/b")]
    digest = hashlib.sha256(b"x").hexdigest()
    clone = Clone(0, reply(RESULT, {"/k/a": digest}))
    seen = probe(clone, "nao1", 11311, files)
    assert len(clone.calls) == 1 and clone.calls[0][:2] == ["bash", "-c"] and clone.calls[0][-2:] == ["/k/a", "/k/b"]
    assert seen.booted and seen.serving and seen.digests == {"/k/a": digest}
    assert clones.same(seen.digests, files[:1]) and not clones.same(seen.digests, files)


def test_probe_says_what_is_not_so():
    files = [BundleFile("a", "x", 0o600, "/k/a")]
    errors = RESULT.replace('"errors": []', '"errors": ["boom"]')
    assert not probe(Clone(0, reply(errors, {})), "nao1", 11311, files).booted
    assert not probe(Clone(0, reply("", {})), "nao1", 11311, files).booted  # no result.json this boot
    assert not probe(Clone(0, reply(RESULT, {}, master="no")), "nao1", 11311, files).serving
    assert not probe(Clone(0, reply(RESULT, {}, vpn="no")), "nao1", 11311, files).serving
    # A probe that did not run through (killed, no bash, garbled): the caller asks the long way.
    assert probe(Clone(124, reply(RESULT, {})), "nao1", 11311, files) is None
    assert probe(Clone(0, "sudo: something\n"), "nao1", 11311, files) is None


def test_a_reused_clone_stays_in_its_partners_relay_config_while_it_is_creating(lab_up):
    fleet, state = lab_up
    writer = StateWriter(fleet, state)
    before = relay_config(fleet, state, "nao1")
    state.robots["nao2"].phase = "creating"  # ensure_clone of nao2, in another thread
    assert sorted(relay_config(fleet, state, "nao1", writer.live())["peers"]) == sorted(before["peers"])
    assert "nao2" not in relay_config(fleet, state, "nao1")["peers"]  # state alone would drop it


def test_reshare_asks_only_clones_whose_config_this_run_does_not_know(lab_up):
    fleet, state = lab_up
    from ccrp_cli.services.knowledge import knowledge_files

    # What ensure_clone leaves for reshare: the relay's config, and the knowledge agent's where it runs.
    known = {r: relay_config_file(fleet, state, r).content + "".join(f.content for f in knowledge_files(fleet, state, r))
             for r in ("nao1", "nao2")}
    clone = Clone(0, "")  # sha256sum prints nothing: the file is not there
    clone.robots = list(state.robots)
    changed = reconcile.reshare(fleet, clone, lambda msg: None, known)
    asked = sorted({robot for robot, _ in clone.pushed})
    assert changed == asked and "nao1" not in asked and "nao2" not in asked and asked
    assert len(clone.calls) == len(asked)  # one digest question per clone not known


def test_reshare_leaves_a_clone_that_stopped_itself_alone(lab_up):
    """A clone its autostop agent powered off is still `ready` in the state: pushing to it would
    fail every command that reshares; it gets the config when it starts again."""
    fleet, state = lab_up
    clone = Clone(0, "", stopped=("turtlebot1",))
    clone.robots = list(state.robots)
    changed = reconcile.reshare(fleet, clone, lambda msg: None)
    assert "turtlebot1" in state.robots and "turtlebot1" not in changed
    assert changed == sorted(set(state.robots) - {"turtlebot1"})


def test_health_times_a_round_trip_to_the_robot_and_status_shows_it():
    """Link quality in `status` and on the dashboard: one ICMP echo from the clone to the robot's
    VPN address (here loopback)."""
    import os

    import pytest

    from ccrp_cli.agent import health
    from ccrp_cli.cli.status import vpn_cell

    if os.geteuid() != 0:
        pytest.skip("a raw ICMP socket needs root, as health.py has on a clone")
    rtt = health.echo_ms("127.0.0.1")
    assert rtt is not None and 0 < rtt < 500
    from ccrp_cli.models.status import StatusRow

    row = dict(robot="nao1", clone="cri-nao1", phase="ready", status="running", state="running", common_ip="10.90.0.10",
               vpn_subnet="10.80.1.0/24", ros_distro="noetic", vpn_connected=True, robot_address="172.30.0.5:1194")
    assert vpn_cell(StatusRow(**row, robot_rtt_ms=12.345)) == "connected 172.30.0.5:1194, rtt 12.3 ms"
    assert vpn_cell(StatusRow(**row)) == "connected 172.30.0.5:1194"
