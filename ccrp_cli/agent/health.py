"""Health of a clone, printed as one JSON object: the VPN (from OpenVPN's management socket) and
the ROS master (XML-RPC). Run on the clone: `python3 health.py [kill <robot>]`. Stdlib only."""

import json
import os
import socket
import sys
import time
import xmlrpc.client

# In a root-only directory (templates/systemd/ccrp-openvpn.service): this script runs as root.
MGMT = "/run/ccrp-openvpn/mgmt.sock"
# In memory on cloud clones: gone after a reboot until ccrp pushes them again.
SERVER_KEY = "/etc/openvpn/server/ccrp/keys/server.key"
MASTER = "http://127.0.0.1:11311"


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
    return {"up": True, "clients": clients}


def master():
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
    print(json.dumps({"vpn": vpn(), "secrets": os.path.exists(SERVER_KEY), "master": master(), "relay": relay()}))


if __name__ == "__main__":
    main()
