"""End to end on Docker: what a local user of a clone, or of a robot, can no longer do.

A one-robot fleet of its own (`e2h<random>`: nao1, its clone and a simulated robot), swept away
at the end of the module whatever happens (`ccrp fleet down`, then everything with its label):

  1. OpenVPN's management socket: a non-root user of the clone cannot connect (its directory is
     root's, 0700), and one that gets past the directory (CAP_DAC_OVERRIDE) is dropped by OpenVPN
     itself (management-client-user root); root, which `vpn revoke` and `status` use, still can,
     and its `client-kill` ends the robot's session, which comes back.
  2. The robot's password is written at each authentication into a 0700 directory of the openvpn
     user on a tmpfs (tmp-dir), deleted after the check, and found nowhere on the clone's disk.
  3. The units' sandboxes are really applied (their own mount namespaces), in the clone and in the
     robot, whose openvpn keeps uid 0 with CAP_NET_ADMIN alone; the containers run with Docker's
     default seccomp profile and no-new-privileges. The power agent's port is systemd's
     (ccrp-power.socket): a local user cannot bind it, even while the agent is stopped, and the
     agent run by hand without it exits 78 at once.
  4. The clone restarted: its robot comes back by itself.
  5. The clone stopped: the robot is "brainless" within seconds (its watchdog runs the fallback
     hooks: the simulated robot's stand-in motors stop), and `ccrp clone start` brings it back.
  6. ROS habits (docs/workloads.md): a catkin workspace's node started as `[rosrun, pkg, script]`
     and another as `[roslaunch, pkg, file.launch]` both publish on the clone, through its one
     master, with nothing added to `apt`.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from ccrp_cli.probe import HEALTH_SCRIPT
from tests.e2e.fleet import (
    CONNECT_TIMEOUT,
    E2EFleet,
    connected,
    exec_in,
    master_probe,
    start_fleet,
    wait_for,
)

pytestmark = [pytest.mark.slow]

ROBOT = "nao1"
MGMT = "/run/ccrp-openvpn/mgmt.sock"
AUTH_TMP = "/run/ccrp-openvpn-auth"
CAP_NET_ADMIN = 1 << 12

# Connects to the management socket and reports what happened, as one JSON line.
MGMT_PROBE = r"""
import json, os, socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
s.settimeout(5)
out = {"uid": os.getuid()}
try:
    s.connect(sys.argv[1])
    out["connected"] = True
    data = b""
    while b"\n" not in data:
        chunk = s.recv(4096)
        if not chunk:
            break
        data += chunk
    out["got"] = data.decode(errors="replace")[:200]
except OSError as exc:
    out["error"] = f"{type(exc).__name__}: {exc}"
print(json.dumps(out))
"""


# A Python catkin package run the two ways a ROS 1 user starts a node: each instance publishes its
# own name on HABITS_TOPIC.
HABITS_TOPIC = "/e2e/habits"
HABITS_PACKAGE = {
    "package.xml": '<?xml version="1.0"?>\n<package format="2"><name>ccrp_e2e_habits</name><version>1.0.0</version>'
                   '<description>e2e</description><maintainer email="e2e@example.org">e2e</maintainer>'
                   '<license>MIT</license><buildtool_depend>catkin</buildtool_depend>'
                   '<exec_depend>rospy</exec_depend></package>\n',
    "CMakeLists.txt": "cmake_minimum_required(VERSION 3.0.2)\nproject(ccrp_e2e_habits)\nfind_package(catkin REQUIRED)\n"
                      "catkin_package()\ncatkin_install_python(PROGRAMS scripts/talk.py DESTINATION "
                      "${CATKIN_PACKAGE_BIN_DESTINATION})\ninstall(DIRECTORY launch DESTINATION "
                      "${CATKIN_PACKAGE_SHARE_DESTINATION})\n",
    "scripts/talk.py": "#!/usr/bin/env python3\nimport rospy\nfrom std_msgs.msg import String\n"
                       "rospy.init_node('talk')\n"
                       f"pub = rospy.Publisher('{HABITS_TOPIC}', String, queue_size=1)\n"
                       "rate = rospy.Rate(5)\nwhile not rospy.is_shutdown():\n"
                       "    pub.publish(String(rospy.get_name()))\n    rate.sleep()\n",
    "launch/talk.launch": '<launch><node pkg="ccrp_e2e_habits" type="talk.py" name="launched" /></launch>\n',
}
HABITS_RUN = [{"name": "rosrun", "command": ["rosrun", "ccrp_e2e_habits", "talk.py"]},
              {"name": "roslaunch", "command": ["roslaunch", "ccrp_e2e_habits", "talk.launch"]}]


def _habits_workspace(tmp_path_factory) -> Path:
    ws = tmp_path_factory.mktemp("habits") / "ws"
    for rel, text in HABITS_PACKAGE.items():
        path = ws / "src" / "ccrp_e2e_habits" / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    (ws / "src" / "ccrp_e2e_habits" / "scripts" / "talk.py").chmod(0o755)
    return ws


@pytest.fixture(scope="module")
def fleet(request, tmp_path_factory) -> E2EFleet:
    def one_robot(data: dict) -> None:
        data.update(robots=[{"name": ROBOT, "type": "nao", "exports": ["/faces"]}])
        data.pop("template", None)
        data["software"] = {"workspace": "ws", "run": HABITS_RUN}

    f = start_fleet(request, tmp_path_factory, "e2h", one_robot, copy={"ws": _habits_workspace(tmp_path_factory)})
    proc = f.inv("fleet", "up", "--json")
    assert proc.returncode == 0, f"fleet up exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr[-3000:]}"
    t0 = time.monotonic()
    f.inv("robot", "sim", "--robot", ROBOT, check=True)
    wait_for(f"{ROBOT} connected", connected(f, ROBOT), CONNECT_TIMEOUT, since=t0)
    return f


@pytest.fixture
def clone(fleet: E2EFleet):
    return fleet.container("clone", ROBOT)


@pytest.fixture
def robot(fleet: E2EFleet):
    return fleet.container("robot-sim", ROBOT)


def sh(container, script: str, *args: str, timeout: int = 30) -> str:
    rc, out = exec_in(container, ["sh", "-c", script, "sh", *args], timeout)
    assert rc == 0, f"`{script}` failed ({rc}) in {container.name}:\n{out[-1500:]}"
    return out


def mgmt_probe(container, *prefix: str) -> dict:
    rc, out = exec_in(container, [*prefix, "python3", "-c", MGMT_PROBE, MGMT])
    assert rc == 0, f"probe as {prefix} failed ({rc}): {out[-800:]}"
    return json.loads(out.strip().splitlines()[-1])


def main_pid(container, unit: str) -> int:
    pid = int(sh(container, f"systemctl show -p MainPID --value {unit}").strip())
    assert pid > 0, f"{unit} is not running in {container.name}"
    return pid


def proc_status(container, pid: int) -> dict[str, str]:
    text = sh(container, f"cat /proc/{pid}/status")
    return dict(line.split(":\t", 1) for line in text.splitlines() if ":\t" in line)


def tunnel_up(fleet: E2EFleet, robot):
    """A probe: the clone lists the robot's session and the robot reaches its master through it
    (the session list alone also shows a client whose authentication just failed)."""
    master = f"http://cri-{ROBOT}:11311"

    def probe() -> tuple[bool, object]:
        row = fleet.status()[ROBOT]
        seen = master_probe(robot, [master]) if row["vpn_connected"] else {}
        return row["vpn_connected"] and seen.get(master, "").startswith("master "), {"status": row, "probe": seen}
    return probe


def server_log(container, since: float) -> str:
    return sh(container, f"journalctl -u ccrp-openvpn --no-pager -o cat --since=@{int(since) - 1}")


# -- 1. the management socket ------------------------------------------------------------------------


def test_management_socket_is_root_only(fleet: E2EFleet, clone):
    assert sh(clone, f"stat -c '%a %U %G' {MGMT.rsplit('/', 1)[0]}").split() == ["700", "root", "root"]
    assert sh(clone, f"test -S {MGMT} && echo socket").strip() == "socket"

    # nobody, as any local user of the clone: the directory stops it before the socket.
    nobody = mgmt_probe(clone, "setpriv", "--reuid=65534", "--regid=65534", "--clear-groups")
    assert nobody["uid"] == 65534 and "PermissionError" in nobody.get("error", ""), nobody

    # A non-root process that passes the directory anyway (CAP_DAC_OVERRIDE): OpenVPN checks the
    # peer's uid and hangs up before its banner (management-client-user root).
    t0 = time.time()
    past_dir = mgmt_probe(clone, "setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                          "--inh-caps=+dac_override", "--ambient-caps=+dac_override")
    assert past_dir["uid"] == 65534 and past_dir.get("connected"), past_dir
    assert ">INFO" not in past_dir.get("got", ""), f"OpenVPN served a non-root management client: {past_dir}"
    refused = "connection rejected -- UID of socket peer (65534) doesn't match required value (0)"
    log = wait_for("OpenVPN logging the refused management client", lambda: (
        refused in (text := server_log(clone, t0)), text[-1500:]), 10)
    fleet.log.append("management socket, non-root past the directory: " +
                     next(line for line in log.splitlines() if refused in line))

    # Root still gets the interface: what `ccrp status` and `vpn revoke` use.
    root = mgmt_probe(clone)
    assert root.get("connected") and root.get("got", "").startswith(">INFO:OpenVPN Management Interface"), root
    row = fleet.status()[ROBOT]
    assert row["vpn_connected"], row


def test_root_kill_through_the_socket_ends_the_session_and_the_robot_returns(fleet: E2EFleet, clone, robot):
    # Another local user holding a connection open must not block root: it is dropped at once.
    holder = sh(clone, "setpriv --reuid=65534 --regid=65534 --clear-groups --inh-caps=+dac_override "
                "--ambient-caps=+dac_override python3 -c 'import socket,sys,time; s=socket.socket(socket.AF_UNIX); "
                "s.connect(sys.argv[1]); time.sleep(30)' \"$1\" >/dev/null 2>&1 & echo started", MGMT)
    assert "started" in holder
    t0 = time.monotonic()
    rc, out = exec_in(clone, ["python3", "-c", HEALTH_SCRIPT(), "kill", ROBOT], timeout=20)
    took = time.monotonic() - t0
    assert rc == 0, out
    assert any(line.startswith("SUCCESS") for line in json.loads(out.strip().splitlines()[-1])["kill"]), out
    fleet.log.append(f"root's client-kill with a non-root client holding the socket: {took:.1f} s")
    assert took < 10, f"the kill took {took:.1f} s"
    # Not revoked: the robot reconnects by itself.
    wait_for(f"{ROBOT}'s tunnel back after the kill", tunnel_up(fleet, robot), CONNECT_TIMEOUT)


# -- 2. the password's temp file ------------------------------------------------------------------------


def test_auth_temp_files_are_in_memory_and_private(fleet: E2EFleet, clone, robot):
    pid = main_pid(clone, "ccrp-openvpn.service")
    argv = sh(clone, f"tr '\\0' ' ' < /proc/{pid}/cmdline")
    assert f"--tmp-dir {AUTH_TMP}" in argv, argv
    assert sh(clone, f"stat -c '%a %U %G' {AUTH_TMP}").split() == ["700", "openvpn", "openvpn"]
    assert sh(clone, f"findmnt -no FSTYPE -T {AUTH_TMP}").strip() == "tmpfs"
    # The robot has authenticated (at least once, by the time the fixture saw it connected), and the
    # check deleted what OpenVPN wrote.
    assert "authentication succeeded for username" in sh(clone, "journalctl -u ccrp-openvpn --no-pager -o cat")
    assert sh(clone, f"ls -A {AUTH_TMP}").strip() == ""

    # OpenVPN really writes there: without the right to, it cannot check the password any more.
    t0 = time.time()
    sh(clone, f"chmod 0500 {AUTH_TMP}")
    try:
        rc, out = exec_in(clone, ["python3", "-c", HEALTH_SCRIPT(),
                                  "kill", ROBOT], timeout=20)
        assert rc == 0, out
        cannot = f"Could not create temporary file '{AUTH_TMP}/"
        log = wait_for("an authentication failing for want of the tmp-dir", lambda: (
            cannot in (text := server_log(clone, t0)) and "Username/Password verification failed" in text,
            text[-2000:]), 30)
        fleet.log.append("tmp-dir not writable: " + next(line for line in log.splitlines() if cannot in line))
    finally:
        sh(clone, f"chmod 0700 {AUTH_TMP}")
    wait_for(f"{ROBOT}'s tunnel back once the tmp-dir is writable again", tunnel_up(fleet, robot), 60)

    # The password itself: nowhere on the clone's file systems (the secrets volume holds its hash).
    password = (fleet.home / fleet.name / "pki" / "passwords" / f"{ROBOT}.txt").read_text().strip()
    assert password
    rc, out = exec_in(clone, ["grep", "-rlF", "--devices=skip", "-e", password,
                              "/etc", "/tmp", "/var", "/run", "/root", "/home", "/opt", "/srv"], timeout=120)
    assert rc == 1 and not out.strip(), f"the robot's password is on the clone (grep rc {rc}): {out[-500:]}"


# -- 3. sandboxes and container privileges ----------------------------------------------------------------


def host_pid(container, marker: str) -> int:
    """The host's pid of the container's process whose command line contains `marker`."""
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/cmdline", "rb") as fh:
                argv = fh.read().replace(b"\0", b" ").decode(errors="replace")
            with open(f"/proc/{entry.name}/cgroup") as fh:
                ours = container.id in fh.read()
        except OSError:
            continue  # gone meanwhile
        if ours and marker in argv:
            found.append(int(entry.name))
    assert len(found) == 1, f"{marker!r} in {container.name}: host pids {found}"
    return found[0]


def test_units_run_in_their_sandboxes(fleet: E2EFleet, clone, robot):
    # Compared from the host: in the container, root has no CAP_SYS_PTRACE and the processes of other
    # users (openvpn after its drop, ccrp-relay) hide their namespaces from it.
    if os.geteuid() != 0:
        pytest.skip("reading other processes' namespaces needs root on the host")
    wait_for(f"{ROBOT}'s tunnel up", tunnel_up(fleet, robot), 60)
    units = [(clone, "/usr/sbin/openvpn --suppress-timestamps --cd"), (robot, "/usr/sbin/openvpn --suppress-timestamps --config"),
             (clone, "/usr/local/lib/ccrp/autostop.py"),  # root, but in a read-only view with no network
             (clone, "/usr/local/lib/ccrp/power.py")]  # the power device's one port on the clone
    if exec_in(clone, ["systemctl", "is-active", "--quiet", "ccrp-relay.service"])[0] == 0:
        units.append((clone, "/usr/local/lib/ccrp/relay.py"))  # when it runs: the relay agent is not what this module tests
    for container, marker in units:
        container.reload()
        own, init = (os.readlink(f"/proc/{pid}/ns/mnt") for pid in (host_pid(container, marker), container.attrs["State"]["Pid"]))
        # ProtectSystem/PrivateTmp need a mount namespace; without one systemd runs the unit
        # unsandboxed and says so only at debug level ("assuming containerized execution").
        assert own != init, f"{marker} in {container.name} runs in PID 1's mount namespace: no sandbox"

    # The power agent listens where the robot's power device reaches it: its own user, no capability.
    status = proc_status(clone, main_pid(clone, "ccrp-power.service"))
    assert status["Uid"].split()[0] != "0" and int(status["CapBnd"], 16) == 0 and status["NoNewPrivs"].strip() == "1", status

    pid = main_pid(robot, "ccrp-vpn.service")
    status = proc_status(robot, pid)
    assert status["Uid"].split()[0] == "0", status["Uid"]
    assert int(status["CapBnd"], 16) == CAP_NET_ADMIN, status["CapBnd"]
    assert int(status["CapEff"], 16) == CAP_NET_ADMIN, status["CapEff"]
    assert status["NoNewPrivs"].strip() == "1"
    rc, out = exec_in(robot, ["nsenter", "-t", str(pid), "-m", "touch", "/etc/ccrp/e2e-write-probe"])
    assert rc != 0 and "Read-only file system" in out, f"ccrp-vpn's view of /etc is writable: {rc} {out}"

    for c in (clone, robot):
        c.reload()
        host = c.attrs["HostConfig"]
        assert sorted(host["CapAdd"] or []) == ["NET_ADMIN", "SYS_ADMIN"], host["CapAdd"]
        assert not any("seccomp=unconfined" in o or "seccomp:unconfined" in o for o in host["SecurityOpt"] or []), \
            host["SecurityOpt"]
        assert any(o.startswith("no-new-privileges") for o in host["SecurityOpt"] or []), host["SecurityOpt"]
        assert not host.get("Privileged")


# Binds the power agent's address and port as the impostor would (IP_FREEBIND, SO_REUSEADDR).
BIND_PROBE = r"""
import socket, sys
s = socket.socket()
s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
s.setsockopt(socket.IPPROTO_IP, 15, 1)
try:
    s.bind((sys.argv[1], int(sys.argv[2])))
    s.listen(1)
    print("bound")
except OSError as exc:
    print(exc.errno)
"""
NOBODY = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]


def test_the_master_runs_as_a_user_of_its_own_without_new_privileges(fleet: E2EFleet, clone):
    """Issue 39, part 3: the ROS master (which fleet up found serving) runs as ccrp-rosmaster, not
    the nodes' `ros`, with no new privileges; its home is its own, which the nodes' user cannot write."""
    status = proc_status(clone, main_pid(clone, "ccrp-rosmaster.service"))
    rc, user = exec_in(clone, ["getent", "passwd", status["Uid"].split()[0]])
    assert user.split(":")[0] == "ccrp-rosmaster" and status["NoNewPrivs"].strip() == "1", (user, status)
    rc, home = exec_in(clone, ["stat", "-c", "%U %a", "/var/lib/ccrp-rosmaster"])
    assert home.split() == ["ccrp-rosmaster", "700"], home
    rc, out = exec_in(clone, ["runuser", "-u", "ros", "--", "touch", "/var/lib/ccrp-rosmaster/e2e-probe"])
    assert rc != 0 and "Permission denied" in out, out


def test_a_local_user_cannot_take_the_power_agents_port(fleet: E2EFleet, clone):
    """Port 11400 is unprivileged: who binds the clone's VPN address there first gets the power
    device's reports and answers `relay: on/off`. systemd holds it (ccrp-power.socket) from boot on
    and while the agent is down, and the agent binds nothing itself."""
    ip = fleet.plan()[ROBOT]["clone_vpn_ip"]
    assert sh(clone, "systemctl show -p Listen --value ccrp-power.socket").strip() == f"{ip}:11400 (Stream)"
    assert sh(clone, "systemctl is-active ccrp-power.socket ccrp-power.service").split() == ["active", "active"]
    taken = lambda: exec_in(clone, [*NOBODY, "python3", "-c", BIND_PROBE, ip, "11400"])[1].strip()  # noqa: E731
    assert taken() == "98"  # EADDRINUSE
    sh(clone, "systemctl stop ccrp-power.service")
    try:
        assert taken() == "98"  # the agent down, its socket still systemd's
        rc, out = exec_in(clone, [*NOBODY, "python3", "/usr/local/lib/ccrp/power.py", "/etc/ccrp/power.json"])
        assert rc == 78 and "ccrp-power: no socket from systemd (" in out, (rc, out)
    finally:
        sh(clone, "systemctl start ccrp-power.service")
    assert main_pid(clone, "ccrp-power.service") > 0


# -- 4. the clone restarted ----------------------------------------------------------------------------------


def test_robot_comes_back_after_the_clone_restarts(fleet: E2EFleet, clone, robot):
    """The robot's tunnel, that is: a restarted ROS master forgets the robot's nodes (ROS 1)."""
    t0 = time.monotonic()
    clone.restart(timeout=20)
    wait_for(f"{ROBOT}'s tunnel back to its restarted clone", tunnel_up(fleet, robot), 90, since=t0)
    fleet.log.append(f"{ROBOT}'s tunnel back {time.monotonic() - t0:.1f} s after `docker restart` of its clone")
    assert sh(clone, f"stat -c '%a %U' {MGMT.rsplit('/', 1)[0]} {AUTH_TMP}").split() == ["700", "root", "700", "openvpn"]


# -- 5. the clone stopped: the brainless robot -----------------------------------------------------------------


def watchdog(robot) -> tuple[str, float]:
    """The robot's watchdog state and when it was written (ccrp-watchdog: "<state> <unix time>")."""
    rc, out = exec_in(robot, ["cat", "/run/ccrp/clone-state"])
    word, _, at = out.strip().partition(" ")
    return (word, float(at)) if rc == 0 and at else ("", 0.0)


def fallback_log(robot) -> list[str]:
    rc, out = exec_in(robot, ["cat", "/var/log/ccrp-fallback.log"])
    return [line.split()[0] for line in out.splitlines()] if rc == 0 else []


def test_robot_without_its_clone_falls_back_and_comes_back(fleet: E2EFleet, clone, robot):
    wait_for(f"{ROBOT}'s tunnel up", tunnel_up(fleet, robot), 60)
    # The watchdog sees the clone back at its next check, which may come a little after the tunnel
    # (after the restart above it may still read "lost" for one interval).
    wait_for(f"{ROBOT}'s watchdog: ok", lambda: (watchdog(robot)[0] == "ok", watchdog(robot)), 15)
    before = len(fallback_log(robot))  # the restart above (section 4) may have made a pair already
    issued = time.time()
    clone.stop(timeout=10)  # the clone's systemd shuts down: OpenVPN and the master end first
    stopped = time.time()
    word, lost_at = wait_for(f"{ROBOT}'s watchdog: lost", lambda: (watchdog(robot)[0] == "lost", watchdog(robot)), 20)
    fleet.log.append(f"{ROBOT} brainless {lost_at - stopped:.1f} s after its clone stopped "
                     f"({lost_at - issued:.1f} s after the stop began, {stopped - issued:.1f} s of shutdown)")
    assert lost_at - stopped <= 6, f"the watchdog took {lost_at - stopped:.1f} s after the clone stopped"
    assert sh(robot, "cat /run/ccrp/sim/motors").split()[0] == "stopped"
    row = fleet.status()[ROBOT]
    assert row["status"] == "exited" and not row["vpn_connected"]

    proc = fleet.inv("clone", "start", "--robot", ROBOT, "--json")
    started = time.time()
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert [r["action"] for r in json.loads(proc.stdout)] == ["started"]
    word, ok_at = wait_for(f"{ROBOT}'s watchdog: ok", lambda: (watchdog(robot)[0] == "ok", watchdog(robot)), 30)
    fleet.log.append(f"{ROBOT} back {ok_at - started:+.1f} s after `ccrp clone start` returned")
    assert ok_at - started <= 6, f"the robot came back {ok_at - started:.1f} s after the clone started"
    assert sh(robot, "cat /run/ccrp/sim/motors").split()[0] == "enabled"
    # The started clone runs a new master, where the robot's node is unknown until it registers
    # again: the watchdog's `new-master` hook starts it again (ROS 1 nodes never re-register).
    # (A new-master of the restart before may land after `before` was read: the order after it counts.)
    def hooks():
        log = fallback_log(robot)[before:]
        lost = log.index("lost") if "lost" in log else len(log)
        return log[lost:lost + 2] == ["lost", "restored"] and "new-master" in log[lost + 2:], log
    wait_for(f"{ROBOT}'s hooks: lost, restored, new-master", hooks, 30)
    wait_for(f"{ROBOT} connected again", tunnel_up(fleet, robot), 30)
    wait_for(f"/{ROBOT}_demo on the new master", lambda: (f"/{ROBOT}_demo" in (r := fleet.status()[ROBOT])["robot_nodes"], r), 30)



# -- 6. ROS habits ---------------------------------------------------------------------------------------

def test_rosrun_and_roslaunch_nodes_publish_through_the_clones_master(fleet: E2EFleet, clone):
    """Issue 43: `[rosrun, pkg, script]` and `[roslaunch, pkg, file.launch]` run as the workspace's
    nodes (rosbash is in the Noetic image; ros-run gives them the workspace's package path), and
    roslaunch used the master the clone runs (ros.env's ROS_MASTER_URI) instead of starting one."""
    echo = ("set -a; . /etc/ccrp/ros.env; set +a; "
            f"exec /usr/local/lib/ccrp/ros-run timeout 20 rostopic echo -n 20 -p {HABITS_TOPIC}")

    def heard() -> tuple[bool, str]:
        rc, out = exec_in(clone, ["sh", "-c", echo], timeout=40)
        return "/talk" in out and "/launched" in out, out[-1500:]
    wait_for("both nodes publishing on the clone", heard, timeout=90)
    for unit in ("ccrp-run-rosrun.service", "ccrp-run-roslaunch.service"):
        assert exec_in(clone, ["systemctl", "is-active", unit])[1].strip() == "active", unit
    # One master on the clone, ccrp-rosmaster's: the launch found it and started none as ros.
    masters = sh(clone, "pgrep -f -u ccrp-rosmaster bin/rosmaster; pgrep -f -u ros bin/rosmaster || true")
    assert len(masters.split()) == 1, masters
    journal = sh(clone, "journalctl -u ccrp-run-roslaunch --no-pager -o cat")
    assert "auto-starting new master" not in journal, journal[-2000:]
