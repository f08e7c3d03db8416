"""Topic-sharing policy: routes, relay configs, `ccrp topics`."""

from __future__ import annotations

import json

import yaml

from ccrp_cli.services.sharing import relay_config, routes
from tests.conftest import LAB


def test_routes_follow_exports_and_imports(lab_up):
    fleet, state = lab_up
    got = {(r.source, r.topic, r.dest, r.local_name) for r in routes(fleet.members(state))}
    assert got == {("nao1", "/faces", "nao2", "/nao1/faces"), ("nao2", "/faces", "nao1", "/nao2/faces"),
                   ("nao1", "/faces", "turtlebot1", "/nao1/faces")}


def test_relay_config_lists_partners_only_and_drops_clones_that_are_down(lab_up):
    fleet, state = lab_up
    cfg = relay_config(fleet, state, "nao1")
    assert sorted(cfg["peers"]) == ["nao2", "turtlebot1"]
    assert cfg["exports"] == ["/faces"]
    assert [i["as"] for i in cfg["imports"]] == ["/nao2/faces"]
    assert cfg["listen"] == "tls/10.90.0.10:7447" and cfg["peers"]["nao2"]["endpoint"] == "tls/10.90.0.11:7447"
    assert "PRIVATE KEY" not in json.dumps(cfg)
    # turtlebot1 exports /map, which nobody imports: its relay exports nothing and talks to nao1 only.
    tb = relay_config(fleet, state, "turtlebot1")
    assert tb["exports"] == [] and sorted(tb["peers"]) == ["nao1"]

    state.robots["nao2"].clear_clone()  # nao2's clone deleted
    cfg = relay_config(fleet, state, "nao1")
    assert sorted(cfg["peers"]) == ["turtlebot1"] and cfg["imports"] == []


def test_partners_are_admitted_by_the_cn_of_their_current_relay_certificate(lab_up):
    """relay.json trusts the relay CA only and names each partner's certificate CN, which the
    agent turns into Zenoh access control; a partner whose relay certificate was revoked drops out."""
    from ccrp_cli.ops import vpn

    fleet, state = lab_up
    cfg = relay_config(fleet, state, "nao1")
    assert cfg["tls"]["ca"].endswith("/relay-ca.crt")
    assert {p: v["cn"] for p, v in cfg["peers"].items()} == {"nao2": "relay-nao2-1", "turtlebot1": "relay-turtlebot1-1"}
    vpn.revoke(fleet, "nao2", cert="relay")
    assert sorted(relay_config(fleet, state, "nao1")["peers"]) == ["turtlebot1"]


def test_topics_command_json(lab_up, ccrp):
    proc = ccrp("topics", "-i", str(LAB), "--json", check=True)
    rows = json.loads(proc.stdout)
    assert {"source": "turtlebot1", "topic": "/map", "dest": None, "as": None} in rows
    assert {"source": "nao1", "topic": "/faces", "dest": "nao2", "as": "/nao1/faces"} in rows


def test_validate_rejects_import_nobody_exports(tmp_path, ccrp):
    data = yaml.safe_load(LAB.read_text())
    data["robots"][2]["imports"] = {"nao2": ["/map"]}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    proc = ccrp("fleet", "validate", "-i", str(bad))
    assert proc.returncode == 2 and "does not export it" in proc.stderr and "Traceback" not in proc.stderr


def test_validate_rejects_reexport_loop(tmp_path, ccrp):
    data = yaml.safe_load(LAB.read_text())
    data["robots"][1]["exports"] = ["/faces", "/nao1/faces"]  # nao2 re-exporting what it imports from nao1
    bad = tmp_path / "loop.yaml"
    bad.write_text(yaml.safe_dump(data))
    proc = ccrp("fleet", "validate", "-i", str(bad))
    assert proc.returncode == 2 and "namespace" in proc.stderr


def test_status_shows_no_sharing_that_is_not_running(lab_up):
    """The relay agent's last report counts only while the agent runs: a stopped agent's stale
    "connected" peers are shown as down, and an agent that never reported still has its peers down."""
    from ccrp_cli.cli.status import relay_peers
    from ccrp_cli.services.sharing import relay_link

    fleet, state = lab_up
    expected = list(relay_config(fleet, state, "nao1")["peers"])
    live = {"relay": {"running": True, "peers": {"nao2": True, "turtlebot1": False}}}
    assert relay_link(live, expected) == (True, {"nao2": True, "turtlebot1": False})
    assert relay_peers(relay_link(live, expected)[1], True) == "1/2 (down: turtlebot1)"
    stale = {"relay": {"running": False, "time": 0, "peers": {"nao2": True, "turtlebot1": True}}}
    never = {"relay": {"running": False, "error": "FileNotFoundError", "peers": {}}}
    for health in (stale, never, {}):
        running, peers = relay_link(health, expected)
        assert (running, peers) == (False, {"nao2": False, "turtlebot1": False})
        assert relay_peers(peers, running) == "0/2 (relay not running)"
    assert relay_peers({}, False) == "-"  # nothing to share with


def test_relay_cns_follow_every_change_of_the_index(lab_up):
    """relay_cns is kept between calls (every clone's config needs it) but must never be stale."""
    fleet, _ = lab_up
    first = fleet.pki.relay_cns()
    assert first["nao1"] == "relay-nao1-1"
    fleet.pki.issue_relay("nao1", "10.90.0.99", 30)  # replaced: a new index.json
    assert fleet.pki.relay_cns()["nao1"] == "relay-nao1-2"
    from ccrp_cli.ops import vpn

    vpn.revoke(fleet, "nao1", cert="relay")
    assert "nao1" not in fleet.pki.relay_cns()
