"""ccrp power agent, on a clone: the clone's end of the line to the robot's power device.

The device (templates/edge/ccrp-power-device) sits on the robot's power line, apart from the
robot's computer, with a VPN client of its own to this clone (CN <robot>.power, a fixed address
that the clone's firewall lets reach this port and nothing else). Every few seconds it connects,
sends its report as one JSON line {"relay": "on"|"off", "robot": "running"|"starting"|"off", "t"},
and gets back one line {"relay": "on"|"off"|null}: the state ccrp asked for (`ccrp robot power
on|off` writes it to WANT as root), null when nothing was asked. The last report is kept in
REPORT, stamped with this clone's clock, for `ccrp robot power` and the clone's health.

The agent binds no port: systemd does (ccrp-power.socket, at boot before any service or login,
FreeBind so before OpenVPN's tun has the address) and passes the listening socket to it (socket
activation). Port 11400 is unprivileged: an agent that bound it itself could find it taken by any
local user who bound it first (at boot, or while the agent restarts), who would then get the
device's reports and answer `relay: on/off`. A socket systemd holds stays held across the agent's
restarts. Started without it, the agent says so and exits NO_SOCKET, which its unit does not restart.

Run by systemd: `python3 power.py /etc/ccrp/power.json` ({"listen": clone VPN address, "port",
"device": the device's VPN address}), with LISTEN_PID/LISTEN_FDS and the socket at fd 3.
Standard library only (no python-systemd).
"""
import json
import os
import socket
import sys
import time

# Both in memory: a wish left from before a reboot, or carried into a snapshot, switches no robot.
WANT = "/run/ccrp-power/want"
REPORT = "/run/ccrp-power/report"
MAX_LINE = 1024
FIRST_FD = 3  # sd_listen_fds(3): where the sockets systemd passes begin
# Started without systemd's socket (by hand, or a unit that lost its Requires=): a mistake no restart
# mends. EX_CONFIG; ccrp-power.service's RestartPreventExitStatus, so it is said once, not in a loop.
NO_SOCKET = 78


def wanted():
    try:
        with open(WANT, encoding="utf-8") as fh:
            word = fh.read().strip()
    except OSError:
        return None
    return word if word in ("on", "off") else None


def read_line(conn):
    data = b""
    while b"\n" not in data:
        chunk = conn.recv(MAX_LINE)
        if not chunk:
            raise ValueError("no report line")
        if len(data) + len(chunk) > MAX_LINE:
            raise ValueError(f"a report over {MAX_LINE} bytes")
        data += chunk
    return data.split(b"\n", 1)[0]


def parse(line):
    """The device's report line, checked, as REPORT's record; an exception for anything else. Who
    holds the device's key and password writes this line: its types are checked, not assumed."""
    report = json.loads(line)
    if not isinstance(report, dict):
        raise TypeError("a report that is not a JSON object")
    relay, robot, t = report.get("relay"), report.get("robot"), report.get("t", 0)
    if relay not in ("on", "off") or robot not in ("running", "starting", "off"):
        raise ValueError(f"a report with relay {relay!r:.40}, robot {robot!r:.40}")
    # The device's own clock, kept for a look at its drift: a number (not a bool), finite, not
    # negative (NaN fails the comparison), before 2100.
    if not isinstance(t, (int, float)) or isinstance(t, bool) or not 0 <= t <= 4102444800:
        raise ValueError(f"a report with t {t!r:.40}")
    return {"relay": relay, "robot": robot, "t": round(time.time(), 3), "device_t": float(t)}


def keep(record):
    """REPORT's one line, replaced whole (the CLI and the clone's health read it any time)."""
    tmp = REPORT + ".tmp"
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(json.dumps(record) + "\n")
    os.replace(tmp, REPORT)


def serve(server, device):
    while True:
        conn, peer = server.accept()
        with conn:
            if peer[0] != device:  # the firewall admits only the device's address: a second lock
                continue
            conn.settimeout(2)  # one device, one short exchange: a stalled one waits at most this
            try:
                keep(parse(read_line(conn)))
                conn.sendall((json.dumps({"relay": wanted()}) + "\n").encode())
            except Exception as exc:  # noqa: BLE001 - whatever one report does (a RecursionError from
                # 1,000 brackets, a type nobody expected), it is dropped: the agent serves the next
                print(f"ccrp-power: a report from {peer[0]} refused: {type(exc).__name__}: {str(exc)[:200]}",
                      file=sys.stderr, flush=True)


def inherited(listen, port):
    """The listening socket systemd passed (socket activation, as sd_listen_fds(3) takes it: LISTEN_PID
    is this process, LISTEN_FDS the count, the first at fd 3), checked to be TCP listening on
    listen:port; or None and why not. The variables go, so no child would take them as its own."""
    pid, count = os.environ.pop("LISTEN_PID", ""), os.environ.pop("LISTEN_FDS", "")
    if (pid, count) != (str(os.getpid()), "1"):
        return None, f"LISTEN_PID {pid[:20]!r}, LISTEN_FDS {count[:20]!r}; this is pid {os.getpid()}"
    try:
        server = socket.socket(fileno=FIRST_FD)  # family and type read from the descriptor
        where = server.getsockname()
        ok = server.type == socket.SOCK_STREAM and server.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN)
    except OSError as exc:
        return None, f"fd {FIRST_FD}: {exc}"
    if not ok or where != (listen, port):
        server.close()
        return None, f"fd {FIRST_FD} is not TCP listening on {listen}:{port}, but {where}"
    os.set_inheritable(FIRST_FD, False)
    server.setblocking(True)  # a passed socket may be non-blocking (the passer's choice); serve() waits in accept()
    return server, None


def main():
    with open(sys.argv[1], encoding="utf-8") as fh:
        cfg = json.load(fh)
    server, problem = inherited(cfg["listen"], int(cfg["port"]))
    if server is None:
        print(f"ccrp-power: no socket from systemd ({problem}): the agent binds no port itself. "
              "Run ccrp-power.service (it takes ccrp-power.socket), not this script", file=sys.stderr, flush=True)
        sys.exit(NO_SOCKET)
    print(f"ccrp-power: serving {cfg['listen']}:{cfg['port']} for the power device at {cfg['device']}", flush=True)
    serve(server, cfg["device"])


if __name__ == "__main__":
    main()
