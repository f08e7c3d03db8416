"""Live-cloud runs shared by tests/live/test_live_<kind>.py: one clone from the fleet's snapshot
through the real commands, a robot connected with its edge bundle, `ccrp status`, `ccrp fleet down`.

Skipped unless the cloud's credentials and CCRP_LIVE_INVENTORY (an inventory of that kind) are
given. Optional:
  CCRP_LIVE_HOME        ccrp's home holding the fleet's state with a baked snapshot (default: a
                        fresh one, and then the test bakes a snapshot first: 10-20 minutes)
  CCRP_LIVE_BASE_IMAGE  --base-image for that bake
  CCRP_LIVE_OPERATOR_CIDR  overrides provider.operator_cidr (your public address/32: SSH to the clone)
See docs/clouds.md. These tests create billable resources and remove them at the end.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT

# What each cloud needs to be reachable, as (env vars all required) alternatives.
CREDENTIALS = {
    "openstack": [("OS_CLOUD",)],
    "gcp": [("GOOGLE_APPLICATION_CREDENTIALS", "CCRP_GCP_PROJECT")],
    "aws": [("AWS_PROFILE",), ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY")],
}
CONNECT_TIMEOUT = 120.0


def marks(kind: str) -> list:
    have = any(all(os.environ.get(v) for v in alt) for alt in CREDENTIALS[kind])
    need = " or ".join("+".join(alt) for alt in CREDENTIALS[kind])
    inventory = os.environ.get("CCRP_LIVE_INVENTORY")
    return [
        pytest.mark.live,
        pytest.mark.skipif(not have, reason=f"live {kind} test: set {need}"),
        pytest.mark.skipif(not inventory, reason="live test: set CCRP_LIVE_INVENTORY to an inventory of that cloud"),
    ]


def one_robot_inventory(kind: str, out: Path) -> tuple[Path, str]:
    """CCRP_LIVE_INVENTORY cut down to its first robot, with the credentials given in the
    environment. The fleet name stays, so a snapshot baked for the fleet is found."""
    data = yaml.safe_load(Path(os.environ["CCRP_LIVE_INVENTORY"]).read_text())
    if data.get("provider", {}).get("kind") != kind:
        pytest.skip(f"CCRP_LIVE_INVENTORY is not a {kind} inventory")
    robot = dict(data["robots"][0])
    robot.pop("imports", None)
    data["robots"], data["template"] = [robot], None
    provider = data["provider"]
    if kind == "openstack":
        provider["cloud"] = os.environ["OS_CLOUD"]
    elif kind == "gcp":
        provider["project"] = os.environ["CCRP_GCP_PROJECT"]
    elif kind == "aws":
        provider["profile"] = os.environ.get("AWS_PROFILE")  # None: the default credential chain
    if os.environ.get("CCRP_LIVE_OPERATOR_CIDR"):
        provider["operator_cidr"] = os.environ["CCRP_LIVE_OPERATOR_CIDR"]
    path = out / f"live-{kind}.yaml"
    path.write_text(yaml.safe_dump({k: v for k, v in data.items() if v is not None}, sort_keys=False))
    return path, robot["name"]


class Ccrp:
    def __init__(self, inventory: Path, home: Path) -> None:
        self.inventory, self.home = inventory, home

    def __call__(self, *args: str, timeout: float = 3600, check: bool = True) -> subprocess.CompletedProcess:
        env = {**os.environ, "CCRP_HOME": str(self.home)}
        env.pop("CCRP_INVENTORY", None)
        proc = subprocess.run([sys.executable, "-m", "ccrp_cli", *args, "-i", str(self.inventory)], cwd=ROOT,
                              env=env, capture_output=True, text=True, timeout=timeout)
        if check and proc.returncode != 0:
            pytest.fail(f"`ccrp {' '.join(args)}` exited {proc.returncode}:\n{proc.stderr[-3000:]}")
        return proc

    def json(self, *args: str):
        return json.loads(self(*args, "--json").stdout)


def _connect_robot(ccrp: Ccrp, robot: str, tmp: Path) -> subprocess.Popen | None:
    """This host plays the robot: `openvpn --config` from its edge bundle. None when it cannot."""
    if shutil.which("openvpn") is None or os.geteuid() != 0 or not Path("/dev/net/tun").exists():
        return None
    bundle = tmp / "edge"
    ccrp("robot", "bundle", robot, "--out", str(bundle))
    log = open(tmp / "openvpn.log", "w")
    # The profile's credentials path is where install.sh puts them; point it at the bundle's copy.
    return subprocess.Popen(["openvpn", "--config", str(bundle / "robot.ovpn"), "--auth-user-pass",
                             str(bundle / "vpn-credentials"), "--dev", "ccrplive"], stdout=log, stderr=subprocess.STDOUT)


def run(kind: str, tmp: Path) -> None:
    inventory, robot = one_robot_inventory(kind, tmp)
    home = Path(os.environ.get("CCRP_LIVE_HOME") or tmp / "home")
    ccrp = Ccrp(inventory, home)
    ccrp("fleet", "validate")
    state = home / yaml.safe_load(inventory.read_text())["fleet"] / "state.json"
    if not (state.exists() and json.loads(state.read_text()).get("snapshot")):
        base = os.environ.get("CCRP_LIVE_BASE_IMAGE")
        ccrp("snapshot", "bake", *(["--base-image", base] if base else []), timeout=2700)
    vpn = None
    try:
        t0 = time.monotonic()
        results = ccrp.json("fleet", "up")
        # "reused": a clone an interrupted live run left behind (removed below).
        assert [r["robot"] for r in results] == [robot] and results[0]["action"] in ("created", "reused"), results
        print(f"{kind}: clone of {robot} ready in {time.monotonic() - t0:.0f} s")
        vpn = _connect_robot(ccrp, robot, tmp)
        if vpn is None:
            pytest.skip("the clone came up; connecting a robot needs root, /dev/net/tun and openvpn here")
        deadline = time.monotonic() + CONNECT_TIMEOUT
        while True:
            row = next(r for r in ccrp.json("status") if r["robot"] == robot)
            if row["vpn_connected"] and row["master_reachable"]:
                break
            assert vpn.poll() is None, (tmp / "openvpn.log").read_text()[-2000:]
            assert time.monotonic() < deadline, f"robot not connected after {CONNECT_TIMEOUT:.0f} s: {row}"
            time.sleep(3)
        print(f"{kind}: robot {robot} connected from {row['robot_address']}")
    finally:
        if vpn is not None:
            vpn.terminate()
            vpn.wait(timeout=30)
        down = ccrp("fleet", "down", check=False)
        assert down.returncode == 0, down.stderr[-3000:]
    # Nothing carrying the fleet's labels is left that state does not know.
    assert ccrp.json("gc", "--dry-run") == []
