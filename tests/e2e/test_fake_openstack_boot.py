"""The fake OpenStack with servers that really boot, driven over real HTTP by plain openstacksdk.

FakeOpenStack(boot=CloudBoot()) served by OpenStackHttp on 127.0.0.1; this test talks to it only
as a separate client would: a clouds.yaml, openstack.connect(cloud=...), the SDK's own requests.
A server is a systemd container booted from the Debian 12 cloud image with the user-data Nova
received; its console (cloud-init's host-key fingerprints) comes through os-getConsoleOutput;
SSH goes to its floating IP with the host key checked against that console; a snapshot
(createImage) boots a second server. No ccrp code is used.

Everything of the run carries ccrp-fake=<run>; the fixture removes it whatever happens and the
test asserts that deleting through the API already left nothing behind.
"""

from __future__ import annotations

import base64
import hashlib
import io
import os
import re
import time

import pytest

from tests.fakes.cloudboot import DEBIAN_12, docker_available, image_buildable

NO_DOCKER = docker_available()

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(NO_DOCKER is not None, reason=f"needs a running Docker engine ({NO_DOCKER})"),
]

docker = pytest.importorskip("docker")
paramiko = pytest.importorskip("paramiko")
openstack = pytest.importorskip("openstack")

from tests.fakes.cloudboot import vendor_data_default_user  # noqa: E402
from tests.fakes.openstack_cloud import BOOT_IMAGE  # noqa: E402
from tests.fakes.openstack_http import booting_cloud  # noqa: E402

CLOUD = "fake-boot"
CIDR = "10.213.47.0/24"   # the tenant network; a Docker network of the run while a server is on it
BOOT_TIMEOUT = 90.0
FP_BLOCK = re.compile(r"-----BEGIN SSH HOST KEY FINGERPRINTS-----(.*?)-----END SSH HOST KEY FINGERPRINTS-----", re.DOTALL)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(openstacksdk connection, fake, boot, http server) for one fake cloud served over HTTP."""
    if not image_buildable():
        pytest.skip(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it")
    t0 = time.monotonic()
    with booting_cloud(tmp_path_factory.mktemp("os"), CLOUD) as http:
        print(f"base image ready in {time.monotonic() - t0:.1f} s")
        boot = http.fake.boot
        saved = {k: os.environ.pop(k) for k in [k for k in os.environ if k.startswith("OS_")]}
        os.environ.update({k: v for k, v in http.environ().items() if v})
        try:
            conn = openstack.connect(cloud=CLOUD)
            yield conn, http.fake, boot, http
            conn.close()
        finally:
            for k in [k for k in os.environ if k.startswith("OS_")]:
                del os.environ[k]
            os.environ.update(saved)
    client = docker.from_env(timeout=60)  # booting_cloud's cleanup left nothing of the run
    run = {"label": f"ccrp-fake={boot.run}"}
    try:
        assert (client.containers.list(ignore_removed=True, all=True, filters=run), client.networks.list(filters=run),
                client.images.list(filters=run)) == ([], [], [])
    finally:
        client.close()


def _key() -> paramiko.Ed25519Key:
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519

    pem = ed25519.Ed25519PrivateKey.generate().private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()).decode()
    return paramiko.Ed25519Key.from_private_key(io.StringIO(pem))


def _public(key) -> str:
    return f"{key.get_name()} {key.get_base64()}"


def _user_data(key) -> str:
    return "\n".join([
        "#cloud-config",
        "users:",
        "  - default",  # the image's own user (debian), which gets the Nova key pair's key
        "  - name: tester",
        "    shell: /bin/bash",
        "    sudo: ALL=(ALL) NOPASSWD:ALL",
        "    lock_passwd: true",
        f"    ssh_authorized_keys: [{_public(key)}]",
        "write_files:",
        "  - path: /etc/ccrp-fake-marker",
        '    content: "booted with this user-data\\n"',
        "",
    ])


def _fingerprints(console: str) -> set[str]:
    """SHA256 fingerprints of the last complete block cloud-init printed."""
    blocks = FP_BLOCK.findall(console.replace("\r", ""))
    return set(re.findall(r"SHA256:([A-Za-z0-9+/]+)", blocks[-1])) if blocks else set()


def _wait_console(conn, server, timeout: float = BOOT_TIMEOUT) -> set[str]:
    deadline = time.monotonic() + timeout
    while True:
        text = conn.compute.get_server_console_output(server)["output"]
        found = _fingerprints(text)
        if found:
            return found
        assert time.monotonic() < deadline, f"no host key fingerprints on the console:\n{text[-3000:]}"
        time.sleep(0.5)


class _Pinned(paramiko.MissingHostKeyPolicy):
    """Accept the server's host key only when its fingerprint is one the console printed."""

    def __init__(self, pins: set[str]) -> None:
        self.pins, self.seen = pins, None

    def missing_host_key(self, client, hostname, key) -> None:
        self.seen = base64.b64encode(hashlib.sha256(key.asbytes()).digest()).decode().rstrip("=")
        if self.seen not in self.pins:
            raise paramiko.SSHException(f"host key SHA256:{self.seen} of {hostname} is not on its console")


def _ssh(ip: str, user: str, key, pins: set[str], timeout: float = 30.0) -> paramiko.SSHClient:
    deadline = time.monotonic() + timeout
    while True:
        client = paramiko.SSHClient()
        policy = _Pinned(pins)
        client.set_missing_host_key_policy(policy)
        try:
            client.connect(ip, username=user, pkey=key, timeout=5, banner_timeout=5, auth_timeout=5,
                           allow_agent=False, look_for_keys=False)
            assert policy.seen in pins
            return client
        except (OSError, paramiko.SSHException) as exc:
            client.close()
            if isinstance(exc, paramiko.SSHException) and "not on its console" in str(exc):
                raise
            assert time.monotonic() < deadline, f"ssh {user}@{ip}: {exc}"
            time.sleep(0.5)


def _run(client: paramiko.SSHClient, command: str) -> str:
    _, out, err = client.exec_command(command, timeout=60)
    rc = out.channel.recv_exit_status()
    text = out.read().decode()
    assert rc == 0, f"{command}: rc={rc} {err.read().decode()}"
    return text


def _boot(conn, name: str, image_id: str, net, subnet, ext, key, keypair: str):
    port = conn.network.create_port(network_id=net.id, fixed_ips=[{"subnet_id": subnet.id}], name=name)
    flavor = conn.compute.find_flavor("m1.small", ignore_missing=False)
    server = conn.compute.create_server(name=name, image_id=image_id, flavor_id=flavor.id, networks=[{"port": port.id}],
                                        key_name=keypair, config_drive=True,
                                        user_data=base64.b64encode(_user_data(key).encode()).decode())
    fip = conn.network.create_ip(floating_network_id=ext.id, port_id=port.id)
    return server, port, fip


def test_servers_boot_console_ssh_snapshot_and_go(served):
    conn, fake, boot, _ = served
    timings: dict[str, float] = {}
    user_key, pair_key = _key(), _key()
    conn.compute.create_keypair(name="operator", public_key=_public(pair_key))
    ext = conn.network.find_network("public", ignore_missing=False)
    assert ext.is_router_external
    net = conn.network.create_network(name="clones")
    subnet = conn.network.create_subnet(network_id=net.id, cidr=CIDR, ip_version=4, name="clones-v4")
    assert subnet.gateway_ip == "10.213.47.1"
    router = conn.network.create_router(name="r", external_gateway_info={"network_id": ext.id})
    conn.network.add_interface_to_router(router, subnet_id=subnet.id)
    base = conn.image.find_image(BOOT_IMAGE, ignore_missing=False)
    assert base.visibility == "public"

    # -- the first server: boots with the user-data, console, SSH pinned from the console --------
    t0 = time.monotonic()
    server, port, fip = _boot(conn, "vm-one", base.id, net, subnet, ext, user_key, "operator")
    fixed = port.fixed_ips[0]["ip_address"]
    assert fixed == "10.213.47.2"  # .1 is the gateway: Neutron's allocation and Docker's agree
    assert fip.floating_ip_address.startswith(fake.fip_cidr.rsplit(".", 1)[0] + ".")
    server = conn.compute.wait_for_server(server, status="ACTIVE", interval=0.5, wait=BOOT_TIMEOUT)
    timings["active"] = time.monotonic() - t0
    addrs = {a["OS-EXT-IPS:type"]: a["addr"] for a in server.addresses["clones"]}
    assert addrs == {"fixed": fixed, "floating": fip.floating_ip_address}
    pins = _wait_console(conn, server)
    timings["console keys"] = time.monotonic() - t0
    tail = conn.compute.get_server_console_output(server, length=5)["output"]
    assert 0 < len(tail.splitlines()) <= 5

    with _ssh(fip.floating_ip_address, "tester", user_key, pins) as ssh:
        timings["ssh"] = time.monotonic() - t0
        assert _run(ssh, "cat /etc/ccrp-fake-marker") == "booted with this user-data\n"
        assert _run(ssh, "hostname").strip() == "vm-one"
        assert _run(ssh, "cloud-init status --wait").strip().endswith("done")
        # Its interfaces hold exactly what Neutron allocated.
        inet = _run(ssh, "ip -4 -o addr show")
        assert f" {fixed}/24 " in inet and f" {fip.floating_ip_address}/24 " in inet
        assert _run(ssh, "sudo -n cat /var/lib/cloud/data/instance-id").strip() == server.id
        # A tmpfs holding a secret: a snapshot must not capture it. A file on the disk: it must.
        _run(ssh, "sudo -n sh -c 'mkdir -p /srv/keys && mount -t tmpfs -o size=1m tmpfs /srv/keys"
                  " && echo secret > /srv/keys/k && echo disk > /srv/on-disk'")
    # The Nova key pair went to the image's default user through the meta-data.
    with _ssh(fip.floating_ip_address, "debian", pair_key, pins) as ssh:
        assert _run(ssh, "id -un").strip() == "debian"

    # -- a snapshot, and a second server from it -----------------------------------------------
    t1 = time.monotonic()
    image = conn.compute.create_server_image(server, "vm-one-snap", metadata={"purpose": "test"})
    image = conn.image.wait_for_status(image, status="active", failures=["killed"], interval=0.5, wait=120)
    timings["snapshot"] = time.monotonic() - t1
    assert fake.docker_images[image.id] in boot.images
    # From now on the cloud's vendor-data names the default user as Ubuntu images do.
    fake.vendor_data = vendor_data_default_user("ubuntu")
    second, port2, fip2 = _boot(conn, "vm-two", image.id, net, subnet, ext, user_key, "operator")
    assert port2.fixed_ips[0]["ip_address"] == "10.213.47.3"
    second = conn.compute.wait_for_server(second, status="ACTIVE", interval=0.5, wait=BOOT_TIMEOUT)
    pins2 = _wait_console(conn, second)
    assert pins2.isdisjoint(pins)  # a new instance: cloud-init made new host keys
    with _ssh(fip2.floating_ip_address, "tester", user_key, pins2) as ssh:
        timings["second ssh"] = time.monotonic() - t1
        assert _run(ssh, "hostname").strip() == "vm-two"
        assert _run(ssh, "cat /srv/on-disk") == "disk\n"
        assert _run(ssh, "ls -A /srv/keys") == ""  # the tmpfs was not on the disk
        # The two servers reach each other on the tenant network.
        assert _run(ssh, f"timeout 5 bash -c 'echo >/dev/tcp/{fixed}/22' && echo ok") == "ok\n"
        assert _run(ssh, "cloud-init status --wait").strip().endswith("done")
    with _ssh(fip2.floating_ip_address, "ubuntu", pair_key, pins2) as ssh:
        assert _run(ssh, "sudo -n id -un").strip() == "root"

    # -- stop and start ------------------------------------------------------------------------
    t2 = time.monotonic()
    conn.compute.stop_server(second)
    conn.compute.wait_for_server(second, status="SHUTOFF", interval=0.5, wait=60)
    assert boot.state(second.id) == "exited"
    conn.compute.start_server(second)
    conn.compute.wait_for_server(second, status="ACTIVE", interval=0.5, wait=60)
    with _ssh(fip2.floating_ip_address, "tester", user_key, pins2, timeout=60) as ssh:
        assert _run(ssh, "cat /srv/on-disk") == "disk\n"
    timings["stop+start"] = time.monotonic() - t2

    # -- everything goes through the API, and nothing of the run is left ------------------------
    for s in (server, second):
        conn.compute.delete_server(s)
    for s in (server, second):
        conn.compute.wait_for_delete(s, interval=0.5, wait=60)
    for f in (fip, fip2):
        conn.network.delete_ip(f)
    for p in (port, port2):
        conn.network.delete_port(p)
    conn.network.remove_interface_from_router(router, subnet_id=subnet.id)
    conn.network.delete_router(router)
    conn.network.delete_network(net)  # its subnet with it
    conn.image.delete_image(image)
    client = boot.client
    run = {"label": f"ccrp-fake={boot.run}"}
    assert client.containers.list(ignore_removed=True, all=True, filters=run) == []
    assert client.images.list(filters=run) == []
    assert [n.name for n in client.networks.list(filters=run)] == [fake.fip_network]  # the fake's own, until cleanup
    print("timings: " + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items()))


def test_a_run_abandoned_mid_boot_leaves_nothing(tmp_path):
    """The client goes away while servers boot and a snapshot is being taken (a failed test):
    leaving booting_cloud removes every container, network and image of the run all the same."""
    if not image_buildable():
        pytest.skip(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it")
    with booting_cloud(tmp_path, CLOUD) as http:
        fake, boot = http.fake, http.fake.boot
        conn = openstack.connect(auth_url=http.auth_url, username="u", password="p", project_name="p",
                                 user_domain_name="default", project_domain_name="default", region_name="RegionOne")
        ext = conn.network.find_network("public", ignore_missing=False)
        net = conn.network.create_network(name="n")
        subnet = conn.network.create_subnet(network_id=net.id, cidr="10.213.48.0/24", ip_version=4)
        base = conn.image.find_image(BOOT_IMAGE, ignore_missing=False)
        first, _, _ = _boot(conn, "a", base.id, net, subnet, ext, _key(), None)
        conn.compute.wait_for_server(first, status="ACTIVE", interval=0.2, wait=BOOT_TIMEOUT)
        conn.compute.create_server_image(first, "a-snap", wait=False)
        _boot(conn, "b", base.id, net, subnet, ext, _key(), None)  # still in BUILD when we leave
        conn.close()
    assert boot.leftovers() == []
    assert fake.wait_idle(0)
