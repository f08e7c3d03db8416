"""Health of a clone, printed as one JSON object: the VPN (from OpenVPN's management socket) and
the ROS master (XML-RPC), or on a ROS 2 clone the graph as the clone sees it (ros2_graph.py, under
the `master` key so that readers stay the same). Run on the clone: `python3 health.py [kill <robot>]`.
Stdlib only."""

import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import time
import xmlrpc.client

# In a root-only directory (templates/systemd/ccrp-openvpn.service): this script runs as root.
MGMT = "/run/ccrp-openvpn/mgmt.sock"
# In memory on cloud clones: gone after a reboot until ccrp pushes them again.
SERVER_KEY = "/etc/openvpn/server/ccrp/keys/server.key"
MASTER = "http://127.0.0.1:11311"
ROS_ENV = "/etc/ccrp/ros.env"
GRAPH = "/usr/local/lib/ccrp/ros2_graph.py"
GRAPH_UNIT = "/etc/systemd/system/ccrp-graph.service"
GRAPH_SOCKET = "/run/ccrp-graph/graph.sock"
# ccrp sets it above 1 for a clone whose CPU is emulated (libvirt without KVM): the graph's query
# took 10.8 s there once, against its 15 s limit.
TIME_SCALE = int(os.environ.get("CCRP_TIME_SCALE") or 1)


def ros_env():
    try:
        with open(ROS_ENV) as fh:
            return dict(line.strip().split("=", 1) for line in fh if "=" in line)
    except OSError:
        return {}


def graph(env):
    """ROS 2: the nodes the clone sees in its robot's domain (a remote one is the robot's, as
    ros2:// URIs on the robot's name, which is how status finds a robot's nodes on a master): what
    ccrp-graph.service's node sees, or on a clone without it (an older ccrp's) a node's own look."""
    data = graph_report() if os.path.exists(GRAPH_UNIT) else graph_once(env)
    robot, me = env.get("CCRP_ROBOT", ""), socket.gethostname()
    data["nodes"] = {n: f"ros2://{robot if where == 'remote' else me}/" for n, where in data["nodes"].items()}
    return data


def graph_report():
    """What ccrp-graph.service's node sees, asked through its socket."""
    data = b""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(10 * TIME_SCALE)
            s.connect(GRAPH_SOCKET)
            while chunk := s.recv(65536):
                data += chunk
        report = json.loads(data)
        if not isinstance(report["nodes"], dict) or not isinstance(report["published_topics"], list):
            raise TypeError("not the graph keeper's report")
        nodes = {str(n): "remote" if w == "remote" else "local" for n, w in report["nodes"].items()}
        topics = [str(t) for t in report["published_topics"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return {"reachable": False, "error": f"ccrp-graph.service did not answer ({type(exc).__name__})",
                "nodes": {}, "published_topics": []}
    return {"reachable": True, "nodes": nodes, "published_topics": topics}


def graph_once(env):
    python = f"/opt/ros/{env.get('ROS_DISTRO', '')}/bin/python"
    logs = tempfile.mkdtemp(prefix="ccrp-graph-")
    try:
        shutil.chown(logs, "ros", "ros")
        run_env = {"PATH": "/usr/bin:/bin", "HOME": "/var/lib/ros", "ROS_LOG_DIR": logs, **env}
        proc = subprocess.run(["/usr/sbin/runuser", "-u", "ros", "--", python, GRAPH, "3"], env=run_env,
                              capture_output=True, text=True, timeout=15 * TIME_SCALE)
        data = json.loads(proc.stdout.strip().splitlines()[-1])
    except (OSError, ValueError, IndexError, subprocess.TimeoutExpired) as exc:
        return {"reachable": False, "error": str(exc)[-200:], "nodes": {}, "published_topics": []}
    finally:
        shutil.rmtree(logs, ignore_errors=True)
    return data


def mgmt(command, until):
    """Send one command to OpenVPN's management socket; read until a line starts with `until`."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(3)
    s.connect(MGMT)
    s.sendall(command.encode() + b"\n")
    data = b""
    while not any(line.startswith(until) for line in data.decode(errors="replace").splitlines()):
        chunk = s.recv(65536)
        if not chunk:
            break
        data += chunk
    s.sendall(b"quit\n")
    s.close()
    return data.decode(errors="replace")


def echo_ms(ip, timeout=0.5):
    """One ICMP echo to `ip` (the robot's VPN address, through the tunnel): the round trip in ms,
    or None. A raw socket: this script runs as root, and the clone image has no ping."""
    ident, seq, payload = os.getpid() & 0xFFFF, 1, b"ccrp-health"
    head = struct.pack("!BBHHH", 8, 0, 0, ident, seq) + payload
    head += b"\0" * (len(head) % 2)  # the checksum is over 16-bit words
    total = sum(struct.unpack(f"!{len(head) // 2}H", head))
    total = (total >> 16) + (total & 0xFFFF)
    packet = struct.pack("!BBHHH", 8, 0, ~(total + (total >> 16)) & 0xFFFF, ident, seq) + payload
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_ICMP) as s:
            t0 = time.monotonic()
            s.sendto(packet, (ip, 0))
            while (left := t0 + timeout - time.monotonic()) > 0:
                s.settimeout(left)
                data, src = s.recvfrom(2048)
                at = (data[0] & 0x0F) * 4
                if src[0] == ip and data[at] == 0 and struct.unpack("!HH", data[at + 4:at + 8]) == (ident, seq):
                    return round((time.monotonic() - t0) * 1000, 2)
    except OSError:  # socket.timeout included
        pass
    return None


def vpn():
    try:
        text = mgmt("status 2", ("END",))
    except OSError as exc:
        return {"up": False, "error": str(exc), "clients": []}
    clients = []
    for line in text.splitlines():
        if line.startswith("CLIENT_LIST,"):
            f = line.split(",")
            clients.append({"cn": f[1], "real_address": f[2], "vpn_ip": f[3], "since": f[7] if len(f) > 7 else "",
                            "client_id": f[10] if len(f) > 10 else ""})
    for c in clients:  # link quality: the round trip to the robot through its tunnel
        c["rtt_ms"] = echo_ms(c["vpn_ip"]) if c["vpn_ip"] else None
    return {"up": True, "clients": clients}


def master():
    env = ros_env()
    if env and "ROS_MASTER_URI" not in env:
        return graph(env)
    try:
        proxy = xmlrpc.client.ServerProxy(MASTER)
        socket.setdefaulttimeout(3)
        code, _, state = proxy.getSystemState("/ccrp_health")
        nodes = sorted({n for group in state for _, names in group for n in names})
        uris = {}
        for n in nodes:
            c, _, uri = proxy.lookupNode("/ccrp_health", n)
            if c == 1:
                uris[n] = uri
        topics = sorted(t for t, _ in state[0])
        return {"reachable": code == 1, "nodes": uris, "published_topics": topics}
    except (OSError, xmlrpc.client.Error) as exc:
        return {"reachable": False, "error": str(exc), "nodes": {}, "published_topics": []}


def relay():
    """The relay agent's own report (written every second), or why there is none."""
    try:
        with open("/run/ccrp-relay/status.json") as fh:
            data = json.load(fh)
    except (OSError, ValueError) as exc:
        return {"running": False, "error": type(exc).__name__, "peers": {}}
    data["running"] = time.time() - data.get("time", 0) < 10
    return data


def service_report(config, status):
    """A platform service's own report (written every second), or why there is none: not
    configured (no pushed config), or not running (no report, or one over 10 s old)."""
    if not os.path.exists(config):
        return {"running": False, "configured": False}
    try:
        with open(status) as fh:
            data = json.load(fh)
    except (OSError, ValueError) as exc:
        return {"running": False, "configured": True, "error": type(exc).__name__}
    data["running"], data["configured"] = time.time() - data.get("time", 0) < 10, True
    return data


def power():
    """The last report of the robot's power device (agent/power.py keeps it), or None."""
    try:
        with open("/run/ccrp-power/report") as fh:
            return fh.readline().strip() or None
    except OSError:
        return None


def nodes(index_path="/etc/ccrp/workloads.json"):
    """The robot's own nodes (docs/workloads.md) as systemd sees them, or None when ccrp put none
    here: state, restarts so far, the digest of what each runs and its `ready` check (as the clone
    keeps it: `ccrp status --ready` runs it)."""
    try:
        with open(index_path) as fh:
            doc = json.load(fh)
        index, ready = doc["nodes"], doc.get("ready") or {}
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    ready = ready if isinstance(ready, dict) else {}
    names = [n for n in index if isinstance(n, str) and n.replace("-", "").isalnum()]
    if not names:
        return []
    props = "ActiveState,SubState,NRestarts"
    try:
        out = subprocess.run(["systemctl", "show", "--property", props, *(f"ccrp-run-{n}.service" for n in names)],
                             capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.TimeoutExpired):
        out = ""
    blocks = [dict(line.split("=", 1) for line in b.splitlines() if "=" in line) for b in out.split("\n\n")]
    rows = []
    for name, b in zip(names, blocks + [{}] * len(names)):
        restarts = b.get("NRestarts", "")
        rows.append({"name": name, "state": b.get("ActiveState") or "unknown", "sub": b.get("SubState") or "",
                     "restarts": int(restarts) if restarts.isdigit() else None, "digest": index[name],
                     "ready_check": ready.get(name)})
    return rows


def knowledge():
    return service_report("/etc/ccrp/knowledge.json", "/run/ccrp-knowledge/status.json")


def api_manager():
    return service_report("/etc/ccrp/api_manager.json", "/run/ccrp-api-manager/status.json")


def main():
    if len(sys.argv) == 3 and sys.argv[1] == "kill":
        # `client-kill <id>` pushes a connection reset to the robot before dropping its instance,
        # so the robot reconnects at once and meets the new CRL. A bare `kill <cn>` drops the
        # instance silently: the robot would go on sending into the void until its ping-restart
        # (60 s) and only then find out. `kill <cn>` stays the fallback (no client id known).
        ids = [c["client_id"] for c in vpn()["clients"] if c["cn"] == sys.argv[2] and c["client_id"]]
        commands = [f"client-kill {cid}" for cid in ids] or ["kill " + sys.argv[2]]
        lines = []
        for command in commands:
            reply = mgmt(command, ("SUCCESS", "ERROR"))
            lines += [line for line in reply.splitlines() if line.startswith(("SUCCESS", "ERROR"))]
        print(json.dumps({"kill": lines}))
        return
    print(json.dumps({"vpn": vpn(), "secrets": os.path.exists(SERVER_KEY), "master": master(), "relay": relay(),
                      "api_manager": api_manager(), "knowledge": knowledge(), "power": power(), "nodes": nodes()}))


if __name__ == "__main__":
    main()
