"""The workspace's code runs in the nodes, never in ccrp's agents (issue 39, part 1; docs/security.md).

ccrp's agents hold its keys (the relay and knowledge agents relay.key, the API manager the Google
key): a workspace package that installs a module named like one they import (`zenoh`, a stdlib
name), a library on LD_LIBRARY_PATH or a setup.sh of its own would run as them. templates/clone/
ros-run gives the workspace only where CCRP_WORKSPACE=1, which only the node units (ccrp-run-*)
set, and drops whatever search path the caller's environment (ros.env, Environment=) carries."""

from __future__ import annotations

import subprocess
from pathlib import Path

from ccrp_cli.services.workloads import node_unit
from ccrp_cli.models.software import RunNode
from tests.conftest import ROOT

ROS_RUN = "/usr/local/lib/ccrp/ros-run"


def test_only_the_node_units_run_with_the_workspace():
    agents = {unit.name: unit.read_text() for unit in sorted((ROOT / "templates" / "systemd").glob("*.service"))
              if unit.name != "ccrp-run.service" and f"ExecStart={ROS_RUN} " in unit.read_text()}
    # Every agent the clone's ROS environment runs: none of them with the workspace.
    assert set(agents) >= {"ccrp-relay.service", "ccrp-knowledge.service", "ccrp-api-manager.service",
                           "ccrp-graph.service", "ccrp-rosmaster.service"}, agents
    settings = {name: [line for line in text.splitlines() if not line.startswith("#")] for name, text in agents.items()}
    assert not [name for name, lines in settings.items() if any("CCRP_WORKSPACE" in line for line in lines)], agents
    node = node_unit(RunNode(name="mapper", command=["python3", "-m", "pkg.node"]), "d1")
    assert "Environment=HOME=/var/lib/ros CCRP_WORKSPACE=1\n" in node, node
    assert f'ExecStart={ROS_RUN} "python3" "-m" "pkg.node"' in node, node


def _clone(tmp_path: Path) -> tuple[Path, dict]:
    """ros-run with the clone's /opt moved under tmp_path: a distro whose setup.sh puts its site (with
    the real `zenoh`) on PYTHONPATH, and a workspace that shadows `zenoh` and `json` in its own site,
    has a lib/ for LD_LIBRARY_PATH and a setup.sh that runs code (a marker file) when sourced."""
    opt = tmp_path / "opt"
    distro_site, ws = opt / "ros" / "fake" / "site", opt / "ccrp" / "workspace"
    ws_site = ws / "lib" / "python3" / "site-packages"
    for d in (distro_site, ws_site):
        d.mkdir(parents=True)
    (distro_site / "zenoh.py").write_text("WHO = 'distro'\n")
    (opt / "ros" / "fake" / "setup.sh").write_text(f'export PYTHONPATH={distro_site}${{PYTHONPATH:+:$PYTHONPATH}}\n')
    for name in ("zenoh", "json"):
        (ws_site / f"{name}.py").write_text(f"open({str(tmp_path / 'imported')!r}, 'a').write({name!r})\nWHO = 'workspace'\n")
    (ws / "setup.sh").write_text(f"touch {tmp_path / 'sourced'}\n"
                                 f"export PYTHONPATH={ws_site}${{PYTHONPATH:+:$PYTHONPATH}}\n"
                                 f"export LD_LIBRARY_PATH={ws / 'lib'}${{LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}}\n"
                                 f"export AMENT_PREFIX_PATH={ws}\n")
    script = tmp_path / "ros-run"
    script.write_text((ROOT / "templates" / "clone" / "ros-run").read_text().replace("/opt/", f"{opt}/"))
    script.chmod(0o755)
    # What a unit's environment could carry in (ros.env, Environment=): the workspace's paths.
    env = {"PATH": "/usr/bin:/bin", "ROS_DISTRO": "fake", "PYTHONPATH": str(ws_site),
           "LD_LIBRARY_PATH": str(ws / "lib"), "AMENT_PREFIX_PATH": str(ws), "HOME": str(tmp_path)}
    return script, env


PROBE = ("import json, os, zenoh; print(zenoh.WHO, json.__name__, os.environ.get('PYTHONPATH'), "
         "os.environ.get('LD_LIBRARY_PATH'), os.environ.get('AMENT_PREFIX_PATH'), os.environ.get('PYTHONNOUSERSITE'))")


def test_an_agent_gets_the_distro_never_the_workspace(tmp_path):
    script, env = _clone(tmp_path)
    out = subprocess.run([str(script), "/usr/bin/python3", "-c", PROBE], env=env, capture_output=True, text=True, check=True)
    distro_site = tmp_path / "opt" / "ros" / "fake" / "site"
    assert out.stdout.split() == ["distro", "json", str(distro_site), "None", "None", "1"], out
    # Nor where the variable says anything but 1.
    other = subprocess.run([str(script), "/usr/bin/python3", "-c", PROBE], env={**env, "CCRP_WORKSPACE": "yes"},
                           capture_output=True, text=True, check=True)
    assert other.stdout == out.stdout, other
    # Neither the workspace's setup.sh nor any of its modules ran.
    assert not (tmp_path / "sourced").exists() and not (tmp_path / "imported").exists()


def test_a_node_gets_the_distro_then_the_workspace(tmp_path):
    script, env = _clone(tmp_path)
    out = subprocess.run([str(script), "/usr/bin/python3", "-c", PROBE], env={**env, "CCRP_WORKSPACE": "1"},
                         capture_output=True, text=True, check=True)
    ws = tmp_path / "opt" / "ccrp" / "workspace"
    who, _, pythonpath, ld_path, ament, _ = out.stdout.split()
    assert who == "workspace" and ament == str(ws) and ld_path == str(ws / "lib"), out
    assert pythonpath.split(":") == [str(ws / "lib" / "python3" / "site-packages"), str(tmp_path / "opt" / "ros" / "fake" / "site")]
    assert (tmp_path / "sourced").exists() and (tmp_path / "imported").read_text() == "jsonzenoh"


def test_a_nodes_roslaunch_waits_for_the_clones_master(tmp_path):
    """ROS 1 habits (docs/workloads.md): `command: [roslaunch, pkg, x.launch]` uses the master the
    clone runs (ccrp-rosmaster, at ros.env's ROS_MASTER_URI), never one of its own, even when that
    one does not answer yet: ros-run adds --wait, for a node only. Other programs keep their words."""
    script, env = _clone(tmp_path)
    tools = tmp_path / "tools"
    tools.mkdir()
    for name in ("roslaunch", "rosrun"):
        (tools / name).write_text(f'#!/bin/sh\necho {name} "$ROS_MASTER_URI" "$@"\n')
        (tools / name).chmod(0o755)
    ws_setup = tmp_path / "opt" / "ccrp" / "workspace" / "setup.sh"
    ws_setup.write_text(f"export PATH={tools}:$PATH\n")  # the programs are the workspace's PATH's here
    env = {**env, "CCRP_WORKSPACE": "1", "ROS_MASTER_URI": "http://10.0.0.1:11311"}

    def run(*argv: str, **extra: str) -> str:
        return subprocess.run([str(script), *argv], env={**env, **extra}, capture_output=True, text=True,
                              check=True).stdout.strip()

    assert run("roslaunch", "my_pkg", "my file.launch") == "roslaunch http://10.0.0.1:11311 --wait my_pkg my file.launch"
    assert run("rosrun", "my_pkg", "node.py", "--wait") == "rosrun http://10.0.0.1:11311 my_pkg node.py --wait"
    assert run(f"{tools}/roslaunch", "my_pkg", "x.launch") == "roslaunch http://10.0.0.1:11311 my_pkg x.launch"
