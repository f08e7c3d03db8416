"""The user's path on a real OpenStack: the single-node Zed of scripts/openstack.sh (Keystone, Glance,
Placement, Nova with the libvirt driver, Neutron with linuxbridge), not a fake. Opt-in:
CCRP_E2E_OPENSTACK_REAL=1 (`make e2e-openstack-real`); about 35 minutes on 2 cores, where Nova
emulates the guests' CPU (TCG), so it is not part of the README's test command.

What a user types, in a directory of their own, against the `ccrp-aio` entry the script wrote to
clouds.yaml: `ccrp init --provider openstack --cloud ccrp-aio` (flavor, external network and this
host's address asked of the cloud), the offloading example's workspace added as the robots' software
and r1's /chatter as a topic r2 imports, `ccrp doctor`, `ccrp snapshot bake` (a
builder instance from the script's Debian 12 image installs ROS 2 Jazzy and the workspace, is
captured, is deleted), `ccrp fleet up` of two clones with floating IPs, `ccrp robot sim` (a simulated
robot on this host dials its clone's floating IP over OpenVPN: certificate and password), r1's
/chatter reaching r2's clone over the fleet's common network, `ccrp deploy` of a new version of the
workspace to the running clones, `ccrp clone stop` / `clone start` (same server, same floating IP),
`ccrp fleet down` and `ccrp snapshot delete`; then the `openstack` CLI lists no server, port,
floating IP, security group, router, network, key pair or image of the fleet. Everything is removed at
the end even on failure. Timings are printed, and written as JSON to $CCRP_OPENSTACK_TIMINGS when set
(bench/openstack_real.py reads them).

CCRP_OPENSTACK_ENTRY=gateway (`make e2e-openstack-real-gateway`) runs the same path with the fleet behind
an entry gateway (provider.entry: gateway) and the project's floating-IP quota lowered to 1, fewer than
its robots: the gateway holds the one floating IP, the clones none, each robot dials its own port of the
gateway's; and the gateway deleted with `openstack server delete` is made again by `fleet up` with the
same address and ports, the robot coming back with the bundle it has.

CCRP_OPENSTACK_CLOUD names another clouds.yaml entry; CCRP_OPENSTACK_KEEP=1 keeps the fleet at the
end and CCRP_OPENSTACK_REUSE=<its directory> runs the tests again on it (no second bake); CCRP_OPENSTACK_TIMEOUT_SCALE (6 here) stretches
the provider's waits for the emulated CPU."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml

from tests.e2e.fleet import wait_for

ROOT = Path(__file__).resolve().parents[2]
CLOUD = os.environ.get("CCRP_OPENSTACK_CLOUD", "ccrp-aio")
SCALE = os.environ.get("CCRP_OPENSTACK_TIMEOUT_SCALE", "6")
GATEWAY = os.environ.get("CCRP_OPENSTACK_ENTRY", "per-clone") == "gateway"
# The cloud's admin (scripts/openstack.sh writes it to clouds.yaml): lowers the project's floating-IP quota.
ADMIN = os.environ.get("CCRP_OPENSTACK_ADMIN_CLOUD", "ccrp-aio-admin")
OFFLOAD = ROOT / "examples" / "offload"
PACKAGE_INIT = Path("ros2/ws/src/ccrp_offload/ccrp_offload/__init__.py")
# A bake from plain Debian under TCG takes 20-30 minutes: the suite's 20-minute limit per test is not this one's.
pytestmark = [pytest.mark.slow, pytest.mark.root, pytest.mark.timeout(5400)]


def _gate() -> str | None:
    if os.environ.get("CCRP_E2E_OPENSTACK_REAL") != "1":
        return "set CCRP_E2E_OPENSTACK_REAL=1 for the user's path on the real OpenStack of scripts/openstack.sh (~35 min)"
    if shutil.which("openstack") is None:
        return "the openstack CLI is missing (bash scripts/openstack.sh installs it with the cloud)"
    proc = subprocess.run(["openstack", "token", "issue", "-f", "value", "-c", "id"], env={**os.environ, "OS_CLOUD": CLOUD},
                          capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        return f"cloud {CLOUD!r} does not answer (bash scripts/openstack.sh starts it): {proc.stderr.strip()[-200:]}"
    return None


SKIP = _gate()
if SKIP:
    pytest.skip(SKIP, allow_module_level=True)


def openstack(*args: str, cloud: str = CLOUD, listing: bool = True) -> list | dict:
    """`openstack ARGS` as JSON (`listing`), or a command that prints nothing (`quota set`)."""
    fmt = ("-f", "json") if listing else ()
    proc = subprocess.run(["openstack", *args, *fmt], env={**os.environ, "OS_CLOUD": cloud},
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, f"openstack {' '.join(args)}: {proc.stderr[-500:]}"
    return json.loads(proc.stdout or "[]")


class Fleet:
    def __init__(self, tmp: Path, name: str) -> None:
        self.dir, self.name, self.timings = tmp / "fleet", name, {}
        self.env = {**os.environ, "CCRP_HOME": str(tmp / "home"), "CCRP_OPENSTACK_TIMEOUT_SCALE": SCALE}
        self.env.pop("CCRP_INVENTORY", None)
        self.env.pop("OS_CLOUD", None)

    def ccrp(self, *args: str, timeout: float = 3600, timed: str | None = None) -> subprocess.CompletedProcess:
        """`ccrp ARGS` run in the fleet's directory, as the user runs it (no -i: ./ccrp.yaml)."""
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-m", "ccrp_cli", *args], cwd=self.dir, env=self.env,
                              capture_output=True, text=True, timeout=timeout)
        if timed:
            self.timings[timed] = round(time.monotonic() - t0, 1)
        return proc

    def ok(self, *args: str, **kw) -> str:
        proc = self.ccrp(*args, **kw)
        assert proc.returncode == 0, f"ccrp {' '.join(args)} exited {proc.returncode}:\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}"
        return proc.stdout

    def status(self) -> dict[str, dict]:
        return {r["robot"]: r for r in json.loads(self.ok("status", "--json", timeout=600))}

    def gateway_name(self) -> str:
        return f"ccrp-{self.name}-gateway-entry-gateway"

    def clone_names(self) -> list[str]:
        return [f"ccrp-{self.name}-cri-r1", f"ccrp-{self.name}-cri-r2"]

    def servers(self) -> dict[str, dict]:
        """The fleet's servers, by name, as the project's `openstack server list` shows them."""
        return {s["Name"]: s for s in openstack("server", "list", "--name", f"^ccrp-{self.name}-")}

    def leftovers(self) -> dict[str, list[str]]:
        """What `openstack` lists of the fleet: by its name prefix, or its ownership tag."""
        tag = f"ccrp-fleet={self.name}"
        prefix = f"ccrp-{self.name}"
        found: dict[str, list[str]] = {}
        for kind in ("server", "port", "floating ip", "security group", "router", "network", "subnet", "keypair",
                     "image"):
            # `--long` adds the tags where the list has it (the security group list shows them as is).
            long = () if kind in ("keypair", "server", "security group") else ("--long",)
            rows = openstack(*kind.split(), "list", *long)
            mine = [r.get("Name") or r.get("ID") for r in rows
                    if str(r.get("Name") or "").startswith(prefix) or tag in (r.get("Tags") or [])
                    or tag in str(r.get("Tags") or r.get("Properties") or "")]
            if mine:
                found[kind] = mine
        return found


def _set_version(fleet: Fleet, version: str) -> None:
    init = fleet.dir / PACKAGE_INIT
    text = init.read_text()
    start = text.index('VERSION = "')
    end = text.index('"', start + len('VERSION = "'))
    init.write_text(text[:start] + f'VERSION = "{version}"' + text[end + 1:])


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("osreal")
    if kept := os.environ.get("CCRP_OPENSTACK_REUSE"):
        # A fleet a run kept (CCRP_OPENSTACK_KEEP=1, or a run killed before its teardown): its
        # directory and CCRP_HOME beside it; the bake is not done again when its snapshot is there.
        f = Fleet(Path(kept), next(p.name for p in (Path(kept) / "home").iterdir()))
        yield from _torn_down(f)
        return
    f = Fleet(tmp, f"osr{secrets.token_hex(2)}")
    f.dir.mkdir()
    shutil.copytree(OFFLOAD / "ros2", f.dir / "ros2", ignore=shutil.ignore_patterns("build", "install", "log"))
    # `--cloud` asks the cloud for the flavor, the external network and this host's address as the
    # clones see it (the external bridge's): the provider section runs as written.
    f.ok("init", "--provider", "openstack", "--cloud", CLOUD, "--robots", "r1,r2", "--fleet", f.name)
    inv = yaml.safe_load((f.dir / "ccrp.yaml").read_text())
    assert inv["provider"] == {"kind": "openstack", "cloud": CLOUD, "flavor": "ccrp.small", "external_network": "public",
                               "operator_cidr": "198.51.100.1/32"}, inv["provider"]
    # What the user adds: a topic to share, and the robots' own software.
    robots = {r["name"]: r for r in inv["robots"]}
    robots["r1"]["exports"] = ["/chatter"]
    robots["r2"]["imports"] = {"r1": ["/chatter"]}
    example = yaml.safe_load((OFFLOAD / "ros2.yaml").read_text())
    inv["software"] = example["software"]
    if GATEWAY:
        inv["provider"]["entry"] = "gateway"
    (f.dir / "ccrp.yaml").write_text(yaml.safe_dump(inv, sort_keys=False))
    with _floating_ip_quota(1 if GATEWAY else None):
        yield from _torn_down(f)


@contextmanager
def _floating_ip_quota(limit: int | None):
    """The ccrp project's floating-IP quota at `limit` for the run (None: as it is), then as it was."""
    if limit is None:
        yield
        return
    project = openstack("token", "issue")["project_id"]
    before = openstack("quota", "show", project, cloud=ADMIN)
    was = before.get("floating-ips", before.get("floating_ips"))
    openstack("quota", "set", "--floating-ips", str(limit), project, cloud=ADMIN, listing=False)
    try:
        yield
    finally:
        openstack("quota", "set", "--floating-ips", str(was), project, cloud=ADMIN, listing=False)


def _torn_down(f: Fleet):
    """The fleet to the tests, then everything of it removed (kept with CCRP_OPENSTACK_KEEP=1)."""
    try:
        yield f
    finally:
        try:
            if os.environ.get("CCRP_OPENSTACK_KEEP") == "1":
                print(f"\nkept fleet {f.name}: CCRP_OPENSTACK_REUSE={f.dir.parent} reuses it")
                return
            f.ccrp("robot", "sim", "--robot", "r1", "--stop", timeout=300)
            f.ccrp("fleet", "down", timeout=1800)
            for snap in json.loads(f.ccrp("snapshot", "list", "--json", timeout=300).stdout or "[]"):
                f.ccrp("snapshot", "delete", snap["id"], "--force", timeout=600)
        finally:
            print(f"\nOpenStack (real) e2e timings (s): {json.dumps(f.timings)}")
            if out := os.environ.get("CCRP_OPENSTACK_TIMINGS"):
                Path(out).write_text(json.dumps(f.timings, indent=1) + "\n")


def test_doctor_reads_the_real_quotas(fleet: Fleet) -> None:
    """Before the bake only the snapshot may be missing; the quotas are real Nova's and Neutron's."""
    checks = {c["check"]: c for c in json.loads(fleet.ccrp("doctor", "--json", timeout=600).stdout)}
    assert {n for n, c in checks.items() if c["status"] == "fail"} <= {"snapshot"}, checks
    quotas = {n: c["detail"] for n, c in checks.items() if n.startswith("quota ")}
    assert len(quotas) == 4 and all(c.startswith("limit ") for c in quotas.values()), quotas
    assert checks["credentials"]["status"] == "ok", checks


def test_bake_makes_the_clone_image_on_the_cloud(fleet: Fleet) -> None:
    if os.environ.get("CCRP_OPENSTACK_REUSE") and json.loads(fleet.ok("snapshot", "list", "--json", timeout=300)):
        pytest.skip("CCRP_OPENSTACK_REUSE: the kept fleet's snapshot is there")
    fleet.ok("snapshot", "bake", timeout=3600, timed="snapshot bake (builder from the Debian 12 image)")
    [snap] = json.loads(fleet.ok("snapshot", "list", "--json", timeout=300))
    [image] = [i for i in openstack("image", "list") if i["ID"] == snap["id"]]
    assert image["Status"] == "active", image
    assert not [n for n in fleet.servers() if "builder" in n], fleet.servers()  # the builder is gone
    fleet.ok("doctor", timeout=600)  # nothing missing now


def test_fleet_up_makes_two_clones_with_floating_ips(fleet: Fleet) -> None:
    rows = json.loads(fleet.ok("fleet", "up", "--json", timeout=3600, timed="fleet up (2 clones)"))
    assert rows, rows
    servers = fleet.servers()
    assert sorted(servers) == sorted(fleet.clone_names() + ([fleet.gateway_name()] if GATEWAY else [])), servers
    assert all(s["Status"] == "ACTIVE" for s in servers.values()), servers
    status = fleet.status()
    for robot in ("r1", "r2"):
        row = status[robot]
        assert row["phase"] == "ready" and row["state"] == "running" and row["secrets"] is True, row
        networks = str(servers[f"ccrp-{fleet.name}-cri-{robot}"]["Networks"])
        if GATEWAY:  # no floating IP: the robot's endpoint is its own port of the gateway's
            assert not row["public_ip"] and "198.51.100." not in networks, (row, networks)
        else:
            assert row["public_ip"].startswith("198.51.100."), row  # the floating IP, on the external network
            assert row["public_ip"] in networks, servers
    if GATEWAY:
        address = _gateway_address(fleet)
        hosts, ports = zip(*(status[r]["vpn_endpoint"].rsplit(":", 1) for r in ("r1", "r2")))
        assert set(hosts) == {address} and len(set(ports)) == 2, status
        # The project's one floating IP (its quota lowered to 1) is the gateway's.
        assert [ip["Floating IP Address"] for ip in openstack("floating ip", "list")] == [address]
    fleet.timings["clone ready (s), from fleet up"] = {r.get("robot"): r.get("seconds") for r in rows if isinstance(r, dict)}


def _gateway_address(fleet: Fleet) -> str:
    """The gateway's floating IP, as the cloud lists it."""
    networks = str(fleet.servers()[fleet.gateway_name()]["Networks"])
    [address] = [ip["Floating IP Address"] for ip in openstack("floating ip", "list")
                 if ip["Floating IP Address"] in networks]
    return address


def test_the_robot_connects_to_its_clone_through_the_floating_ip(fleet: Fleet) -> None:
    result = json.loads(fleet.ok("robot", "sim", "--robot", "r1", "--wait", "900", "--json", timeout=1200,
                                 timed="robot sim --wait (r1)"))
    assert result["nodes"] == ["/r1_demo"], result
    row = fleet.status()["r1"]
    assert row["vpn_connected"] is True and "/r1_demo" in row["robot_nodes"], row
    if GATEWAY:  # the gateway's own address: it forwards the robot's packets as its own (SNAT)
        assert row["robot_address"].startswith("10."), row
    else:
        assert row["robot_address"].startswith("198.51.100.1:"), row  # this host, through the floating IP


def test_a_topic_r1_exports_reaches_r2s_clone_over_the_common_network(fleet: Fleet) -> None:
    t0 = time.monotonic()
    out = fleet.ok("clone", "exec", "--robot", "r2", "--", "ccrp-topic", "echo", "/r1/chatter", "-n", "2", "-t", "300",
                   timeout=900)
    fleet.timings["relay: first 2 messages of r1's /chatter on r2's clone"] = round(time.monotonic() - t0, 1)
    assert out.count('{"data": "hello from r1 #') == 2, out[-2000:]
    wait_for("r2's relay link to r1", lambda: ((row := fleet.status()["r2"]).get("relay_peers") == {"r1": True}, row),
          timeout=300, interval=5)


def _started(fleet: Fleet, robot: str, version: str) -> tuple[bool, str]:
    proc = fleet.ccrp("logs", "--robot", robot, "mapper", "--lines", "300", timeout=300)
    return f"ccrp_offload {version} started" in proc.stdout, proc.stdout[-1000:] + proc.stderr[-500:]


def test_deploy_brings_a_new_version_to_the_running_clones(fleet: Fleet) -> None:
    before = fleet.servers()
    wait_for("mapper 1.0 on r1's clone", lambda: _started(fleet, "r1", "1.0"), timeout=600, interval=5)
    _set_version(fleet, "1.1")
    rows = json.loads(fleet.ok("deploy", "--json", timeout=3600, timed="deploy (2 clones)"))
    assert sorted((r["robot"], r["action"]) for r in rows) == [("r1", "deployed"), ("r2", "deployed")], rows
    for robot in ("r1", "r2"):
        wait_for(f"mapper 1.1 on {robot}'s clone", lambda r=robot: _started(fleet, r, "1.1"), timeout=600, interval=5)
    after = fleet.servers()
    assert {n: s["ID"] for n, s in after.items()} == {n: s["ID"] for n, s in before.items()}  # the same servers
    assert [r["action"] for r in json.loads(fleet.ok("deploy", "--json", timeout=1200))] == ["current", "current"]


def test_the_gateway_made_again_keeps_the_address_and_the_robot_comes_back(fleet: Fleet) -> None:
    """The gateway deleted in the cloud (an operator's `openstack server delete`): `fleet up` makes it
    again from the state, with the same floating IP and ports, and r1 reconnects with the bundle it has."""
    if not GATEWAY:
        pytest.skip("the fleet has no entry gateway (CCRP_OPENSTACK_ENTRY=gateway)")
    before = fleet.status()["r1"]["vpn_endpoint"]
    address = _gateway_address(fleet)
    old = fleet.servers()[fleet.gateway_name()]["ID"]
    openstack("server", "delete", "--wait", old, listing=False)
    rows = json.loads(fleet.ok("fleet", "up", "--json", timeout=3600, timed="fleet up (gateway made again)"))
    assert sorted(r["robot"] for r in rows) == ["r1", "r2"], rows
    assert fleet.servers()[fleet.gateway_name()]["ID"] != old and _gateway_address(fleet) == address
    t0 = time.monotonic()
    wait_for("r1 back through the new gateway",
             lambda: ((row := fleet.status()["r1"])["vpn_connected"] is True and "/r1_demo" in row["robot_nodes"]
                      and row["vpn_endpoint"] == before, row), timeout=900, interval=10)
    fleet.timings["robot back after the gateway was made again (s)"] = round(time.monotonic() - t0, 1)


def test_clone_stop_and_start_keep_the_server_and_its_floating_ip(fleet: Fleet) -> None:
    name = f"ccrp-{fleet.name}-cri-r2"
    before = fleet.servers()[name]
    ip = fleet.status()["r2"]["public_ip"] or fleet.status()["r2"]["vpn_endpoint"]
    fleet.ok("clone", "stop", "--robot", "r2", timeout=1800, timed="clone stop (r2)")
    assert fleet.servers()[name]["Status"] == "SHUTOFF"
    fleet.ok("clone", "start", "--robot", "r2", timeout=3600, timed="clone start (r2), to serving")
    server = fleet.servers()[name]
    assert server["ID"] == before["ID"] and server["Status"] == "ACTIVE", server
    row = fleet.status()["r2"]
    assert (row["public_ip"] or row["vpn_endpoint"]) == ip and row["phase"] == "ready" and row["state"] == "running", row
    # The restarted clone runs the deployed version, and r1's topic reaches it again.
    wait_for("mapper 1.1 on r2's restarted clone", lambda: _started(fleet, "r2", "1.1"), timeout=600, interval=5)
    out = fleet.ok("clone", "exec", "--robot", "r2", "--", "ccrp-topic", "echo", "/r1/chatter", "-n", "1", "-t", "300",
                   timeout=900)
    assert '{"data": "hello from r1 #' in out, out[-2000:]


def test_fleet_down_and_snapshot_delete_leave_nothing_of_the_fleet(fleet: Fleet) -> None:
    fleet.ok("robot", "sim", "--robot", "r1", "--stop", timeout=300)
    fleet.ok("fleet", "down", timeout=1800, timed="fleet down")
    snaps = json.loads(fleet.ok("snapshot", "list", "--json", timeout=300))
    for snap in snaps:
        fleet.ok("snapshot", "delete", snap["id"], "--force", timeout=600)
    assert fleet.leftovers() == {}
