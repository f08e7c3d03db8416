"""Renderers: golden files, cloud-init's own validator, no private key in user-data, size limits."""

from __future__ import annotations

import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from ccrp_cli.errors import CcrpError
from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.render import bundles, cloudinit, network, openvpn
from ccrp_cli.services.registry import boots
from ccrp_cli.providers import info
from ccrp_cli.models.layout import SECRETS_DIR
from tests.conftest import INVENTORIES, ROOT

GOLDEN = ROOT / "tests" / "golden"


def golden(name: str, text: str) -> None:
    """Compare with tests/golden/<name>; CCRP_UPDATE_GOLDEN=1 rewrites the file."""
    path = GOLDEN / name
    if os.environ.get("CCRP_UPDATE_GOLDEN") == "1":
        path.write_text(text)
    assert path.exists(), f"missing golden file {path}; run with CCRP_UPDATE_GOLDEN=1"
    assert text == path.read_text(), f"{name} differs from its golden file"


def _redact(text: str) -> str:
    """Replace key material (random on every run) so the rest can be compared exactly."""
    return re.sub(r"(<(ca|cert|key|tls-crypt)>\n).*?(\n</\2>)", r"\1...\3", text, flags=re.S)


@pytest.fixture
def view(lab):
    return clone_view(lab, lab.store.load_state(), "nao1")


def test_golden_clone_files(view):
    golden("nao1.server.conf", openvpn.server_conf(view))
    golden("nao1.ccd", openvpn.ccd_entry(view))
    fw4, fw6 = network.firewall_rules(view)
    golden("nao1.firewall.rules", fw4)
    golden("nao1.firewall6.rules", fw6)
    golden("nao1.clone.hosts", network.clone_hosts_file(view))
    golden("nao1.clone.ros.env", network.ros_env(view, "clone"))
    golden("nao1.user-data.yaml", cloudinit.user_data(view, boots()))


def test_golden_robot_files(lab, view):
    creds = lab.pki.credentials("nao1")
    golden("nao1.robot.ovpn", _redact(openvpn.client_profile(view, creds, "203.0.113.10")))
    golden("nao1.robot.hosts", network.hosts_block(view, "robot"))
    golden("nao1.robot.ros.env", network.ros_env(view, "robot"))
    golden("nao1.robot.chrony.conf", network.chrony_conf(view, "robot"))


def test_client_profile_carries_its_own_material(lab, view):
    creds = lab.pki.credentials("nao1")
    text = openvpn.client_profile(view, creds, "clone.example.org:443")
    assert "remote clone.example.org 443\n" in text
    assert creds.client_key_pem.strip() in text and creds.tls_crypt_key.strip() in text
    assert "verify-x509-name cri-nao1 name" in text and "auth-nocache" in text
    assert creds.server_key_pem.strip() not in text


def test_vpn_configs_follow_the_design(view):
    conf = openvpn.server_conf(view)
    for line in (
        "tls-version-min 1.2", "data-ciphers AES-256-GCM:CHACHA20-POLY1305", "tls-crypt keys/tc.key",
        "remote-cert-tls client", "tls-verify ccrp-auth", "crl-verify keys/crl.pem",
        "auth-user-pass-verify ccrp-auth via-file", "user openvpn", "persist-key", "persist-tun",
        "topology subnet", "allow-compression no",
    ):
        assert f"\n{line}\n" in conf, line
    # Forbidden: compression and several robots sharing one certificate.
    for banned in ("comp-lzo", "compress", "duplicate-cn", "client-to-client"):
        assert not re.search(rf"^{banned}\b", conf, re.M), banned


def test_master_port_is_only_open_through_the_vpn(view):
    fw4, fw6 = network.firewall_rules(view)
    assert ":INPUT DROP" in fw4 and ":INPUT DROP" in fw6
    accepts = [line for line in fw4.splitlines() if line.startswith("-A INPUT") and "ACCEPT" in line]
    assert "-A INPUT -p udp --dport 1194 -j ACCEPT" in accepts
    # Only loopback, established flows, ICMP, the VPN port, the tunnel itself and the relay
    # port from the common network are accepted; nothing else from anywhere.
    open_to_all = [a for a in accepts if " -s " not in a and " -i " not in a and "ctstate" not in a]
    assert open_to_all == ["-A INPUT -p icmp -j ACCEPT", "-A INPUT -p udp --dport 1194 -j ACCEPT"]
    assert "11311" not in fw4


def _all_views(tmp_path_factory_home):
    for path in INVENTORIES:
        fleet = Fleet.open(path)
        state = fleet.store.load_state()
        for robot in fleet.members(state):
            yield path.stem, clone_view(fleet, state, robot.name)


@pytest.mark.skipif(shutil.which("cloud-init") is None, reason="cloud-init not installed (apt-get install cloud-init)")
def test_every_user_data_passes_cloud_init_schema(ccrp_home, tmp_path):
    checked = 0
    for stem, view in _all_views(ccrp_home):
        for bare in (False, True):
            keys = ["ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFakeKeyForSchemaOnly operator"] if stem != "lab" else None
            text = cloudinit.user_data(view, boots(), install_packages=bare, login_keys=keys)
            assert text.startswith("#cloud-config\n")
            assert "PRIVATE KEY" not in text and "Static key" not in text
            info(view.inv.provider.kind).fit_user_data(text)
            f = tmp_path / f"{stem}-{view.name}-{bare}.yaml"
            f.write_text(text)
            proc = subprocess.run(["cloud-init", "schema", "--config-file", str(f)], capture_output=True, text=True)
            assert proc.returncode == 0 and "Valid cloud-config" in proc.stdout, proc.stdout + proc.stderr
            checked += 1
    assert checked >= 2 * 9


def test_cloud_clones_keep_their_keys_in_memory(ccrp_home):
    """Cloud user-data mounts a tmpfs on the keys directory at every boot (bootcmd); a Docker
    clone has its secrets volume there instead."""
    kinds = set()
    for _stem, view in _all_views(ccrp_home):
        data = cloudinit.user_data_dict(view, boots())
        kinds.add(view.inv.provider.kind)
        if view.inv.provider.kind == "docker":
            assert "bootcmd" not in data
            continue
        hosts, mkdir, mount = data["bootcmd"]
        assert hosts[-1] == "/etc/ccrp/hosts" and 'cp "$0" /etc/hosts' in hosts[2]
        assert mkdir == ["mkdir", "-p", SECRETS_DIR]
        assert mount[-1] == SECRETS_DIR and "mount -t tmpfs -o mode=0700" in mount[2]
    assert kinds == {"docker", "openstack", "gcp", "aws"}
    # The server config names every key under keys/; nothing else of OpenVPN's lives there.
    conf = openvpn.server_conf(view)
    assert {line.split()[1] for line in conf.splitlines() if line.startswith(("ca ", "cert ", "key ", "tls-crypt ", "crl-verify "))} == {
        "keys/ca.crt", "keys/server.crt", "keys/server.key", "keys/tc.key", "keys/crl.pem"}


def test_user_data_never_carries_key_material(view, monkeypatch):
    data = cloudinit.user_data_dict(view, boots())
    data["write_files"].append({"path": "/x", "content": "-----BEGIN PRIVATE KEY-----\n"})
    with pytest.raises(CcrpError, match="key material"):
        cloudinit.dump(data)


def test_user_data_size_limits():
    small = "#cloud-config\n" + "a: b\n"
    assert info("aws").fit_user_data(small) == (small.encode(), False)
    # Repetitive text gzips well: over AWS's raw limit, gzip makes it fit.
    big = "#cloud-config\n" + "x: " + "y" * 20_000 + "\n"
    payload, gz = info("aws").fit_user_data(big)
    assert gz and len(payload) <= 16_384
    # GCE does not take gzip: refused with the figure and the limit.
    random_text = os.urandom(200_000).hex()
    with pytest.raises(CcrpError, match=r"over gcp's limit of 262144 bytes"):
        info("gcp").fit_user_data(random_text)
    with pytest.raises(CcrpError, match=r"over aws's limit of 16384 bytes even gzipped"):
        info("aws").fit_user_data(random_text[:40_000])


def test_clone_secrets_bundle(lab, view, tmp_path):
    out = bundles.write_bundle(tmp_path / "s", bundles.clone_secrets(view, lab.pki.credentials("nao1")), {"robot": "nao1"})
    names = {p.name: stat.S_IMODE(p.stat().st_mode) for p in out.iterdir()}
    assert names == {"ca.crt": 0o644, "crl.pem": 0o644, "server.crt": 0o644, "server.key": 0o600, "tc.key": 0o600,
                     "passwd": 0o640, "manifest.json": 0o644}
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    manifest = yaml.safe_load((out / "manifest.json").read_text())
    assert {f["dest"] for f in manifest["files"]} >= {"/etc/openvpn/server/ccrp/keys/server.key"}
    assert (out / "passwd").read_text().startswith("nao1:$scrypt$")
    assert lab.pki.credentials("nao1").password not in (out / "passwd").read_text()


def test_edge_bundle_installs_idempotently(lab, view, tmp_path):
    out = bundles.write_bundle(
        tmp_path / "edge", bundles.edge_bundle(view, lab.pki.credentials("nao1"), "203.0.113.10"), {"robot": "nao1"}
    )
    assert stat.S_IMODE((out / "robot.ovpn").stat().st_mode) == 0o600
    assert stat.S_IMODE((out / "vpn-credentials").stat().st_mode) == 0o600
    assert (out / "vpn-credentials").read_text().splitlines()[0] == "nao1"
    root = tmp_path / "robot-root"
    (root / "etc" / "chrony" / "conf.d").mkdir(parents=True)
    (root / "etc" / "hosts").write_text("127.0.0.1\tlocalhost\n10.1.1.1\tprinter\n")
    for _ in range(2):
        subprocess.run(["sh", str(out / "install.sh")], env={**os.environ, "CCRP_ROOT": str(root)}, check=True,
                       capture_output=True)
    hosts = (root / "etc" / "hosts").read_text()
    assert hosts.count("# BEGIN ccrp") == 1 and "10.1.1.1\tprinter" in hosts
    assert "10.80.1.1       cri-nao1\n" in hosts and "cri-nao2" not in hosts  # a robot sees only its clone
    assert stat.S_IMODE((root / "etc/ccrp/robot.ovpn").stat().st_mode) == 0o600
    # Users reach ros.env by name (their ROS environment), not the directory's list; secrets are 0600.
    assert stat.S_IMODE((root / "etc/ccrp").stat().st_mode) == 0o711
    assert stat.S_IMODE((root / "etc/ccrp/ros.env").stat().st_mode) == 0o644
    assert "ROS_MASTER_URI=http://cri-nao1:11311" in (root / "etc/ccrp/ros.env").read_text()
    assert (root / "etc/chrony/conf.d/ccrp.conf").read_text().startswith("# ccrp: take time from clone")
    assert (root / "etc/systemd/system/ccrp-vpn.service").exists()


def _wait_for(path: Path, value: str, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and path.read_text().split()[:1] == [value]:  # "<state> <unix time>"
            return
        time.sleep(0.05)
    raise AssertionError(f"{path} never became {value!r}")


def test_watchdog_switches_to_fallback_and_back(tmp_path):
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    hooks = tmp_path / "fallback.d"
    hooks.mkdir()
    events = tmp_path / "events"
    hook = hooks / "10-record"
    hook.write_text(f"#!/bin/sh\necho \"$1\" >> {events}\n")
    hook.chmod(0o755)
    state = tmp_path / "state"
    env = {"PATH": os.environ["PATH"], "CCRP_CLONE_HOST": "127.0.0.1", "CCRP_MASTER_PORT": str(port),
           "CCRP_WATCHDOG_INTERVAL": "0.1", "CCRP_WATCHDOG_FAIL_AFTER": "3",
           "CCRP_WATCHDOG_STATE": str(state), "CCRP_FALLBACK_DIR": str(hooks)}
    proc = subprocess.Popen([sys.executable, str(ROOT / "templates/edge/ccrp-watchdog")], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        _wait_for(state, "ok")
        listener.close()  # the clone disappears
        _wait_for(state, "lost")
        listener = socket.create_server(("127.0.0.1", port))
        _wait_for(state, "ok")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and events.read_text().split() != ["lost", "restored"]:
            time.sleep(0.05)
        assert events.read_text().split() == ["lost", "restored"]
    finally:
        proc.kill()
        proc.wait()
        listener.close()


def test_watchdog_tells_the_hooks_of_a_new_master(tmp_path):
    """A ROS 1 node never registers again with a restarted master: a changed /run_id (what
    roscore sets at each start) runs the hooks with `new-master`, once per change; the master
    answering again with the same run_id (a tunnel blip) does not."""
    from xmlrpc.server import SimpleXMLRPCServer

    run_id = ["first-run"]
    server = SimpleXMLRPCServer(("127.0.0.1", 0), logRequests=False, allow_none=True)
    server.register_function(lambda caller, key: [1, "", run_id[0]] if key == "/run_id" else [-1, "no", 0], "getParam")
    threading.Thread(target=server.serve_forever, daemon=True).start()
    hooks, events, state = tmp_path / "fallback.d", tmp_path / "events", tmp_path / "state"
    hooks.mkdir()
    (hooks / "10-record").write_text(f"#!/bin/sh\necho \"$1\" >> {events}\n")
    (hooks / "10-record").chmod(0o755)
    env = {"PATH": os.environ["PATH"], "CCRP_CLONE_HOST": "127.0.0.1", "CCRP_MASTER_PORT": str(server.server_address[1]),
           "CCRP_WATCHDOG_INTERVAL": "0.1", "CCRP_WATCHDOG_STATE": str(state), "CCRP_FALLBACK_DIR": str(hooks)}
    proc = subprocess.Popen([sys.executable, str(ROOT / "templates/edge/ccrp-watchdog")], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        _wait_for(state, "ok")
        time.sleep(0.5)  # several checks of the same master
        assert not events.exists()
        run_id[0] = "second-run"
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not events.exists():
            time.sleep(0.05)
        time.sleep(0.5)
        assert events.read_text().split() == ["new-master"]
    finally:
        proc.kill()
        proc.wait()
        server.shutdown()
        server.server_close()


def test_every_backend_runs_the_one_debian_platform():
    """Docker and the three clouds run the same recipe platform: Debian 12 with Debian's own ROS 1
    packages and OpenVPN 2.6 (the rendered server.conf's data-ciphers needs OpenVPN 2.5 or newer)."""
    from ccrp_cli.providers import REGISTRY
    from ccrp_cli.recipes import recipe

    assert {k: i.platform for k, i in REGISTRY.items()} == dict.fromkeys(("docker", "openstack", "gcp", "aws", "libvirt"), "debian-bookworm")
    assert list(recipe("noetic").platforms) == ["debian-bookworm"]


def test_cloud_image_config_installs_what_the_docker_snapshot_has():
    """The cloud-config a builder (or a bare clone) runs and the Dockerfile of the Docker snapshot:
    the same packages, pip packages, relay agent and locale command."""
    from ccrp_cli.providers.docker import images
    from ccrp_cli.recipes import platform

    from ccrp_cli.loader import load_inventory

    docker_plat = platform("noetic", "debian-bookworm")
    from ccrp_cli.services.registry import image_agents

    dockerfile = images.dockerfile("lab", "noetic", images.DEFAULT_BASE, docker_plat, agents=image_agents())
    for path in INVENTORIES:
        inv = load_inventory(path)
        if inv.ros.ros2:  # Docker only so far: its image's venv step has no cloud-config twin
            continue
        data = cloudinit.image_config(inv, image_agents())
        assert data["packages"] == docker_plat.packages
        assert f"for p in {' '.join(docker_plat.packages)}; do" in dockerfile
        assert data["runcmd"][0] == ["sh", "-c", cloudinit.LOCALE_SETUP] and cloudinit.LOCALE_SETUP in dockerfile
        assert data["runcmd"][1][-len(docker_plat.pip):] == docker_plat.pip and " ".join(docker_plat.pip) in dockerfile
        assert [f["path"] for f in data["write_files"]] == ["/usr/local/lib/ccrp/relay.py",
                                                            "/usr/local/lib/ccrp/api_manager.py"]
        assert "COPY relay.py api_manager.py /usr/local/lib/ccrp/" in dockerfile


def test_agents_in_user_data_lose_comments_and_docstrings_only():
    """User-data has a hard size limit (AWS: 16 KiB gzipped), so the agents it carries lose their
    comments, blank lines and docstrings; strings (scripts with blank lines and #) stay whole, a
    function that was only a docstring keeps a body, and what is not the same program is not used."""
    src = ('#!/usr/bin/python3\n"""Module doc."""\nfrom __future__ import annotations\n\nSCRIPT = """\nline # not a comment\n\n'
           'end\n"""\n\n\ndef only_doc():\n    """Nothing else."""\n\n\ndef f(x):  # trailing\n    # whole line\n'
           '    """Doc\n    on two lines."""\n    return x + 1  # why\n\nclass C: "one-liner kept"\n')
    out = cloudinit.compact_python(src)
    assert out == ('#!/usr/bin/python3\nfrom __future__ import annotations\nSCRIPT = """\nline # not a comment\n\nend\n"""\n'
                   'def only_doc():\n    pass\ndef f(x):\n    pass\n    return x + 1\nclass C: "one-liner kept"\n')
    namespace: dict = {}
    exec(compile(out, "agent", "exec"), namespace)
    assert namespace["f"](1) == 2 and namespace["only_doc"]() is None and namespace["SCRIPT"].count("\n") == 4
    assert cloudinit.compact_python("x = (1,\n# inside brackets\n     2)\n") == "x = (1,\n     2)\n"
    for agent in sorted((ROOT / "ccrp_cli" / "agent").glob("*.py")):
        text = agent.read_text()
        compact = cloudinit.compact_python(text)
        if agent.name != "__init__.py":
            assert len(compact) < 0.9 * len(text), agent.name  # the fallback (src as it is) was not taken
        compile(compact, agent.name, "exec")
