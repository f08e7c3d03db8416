"""The GCE fake whose instances really boot (tests/fakes/gce_boot.py), driven with plain compute_v1
calls and no ccrp in between: an instance boots from the debian-12 family and answers SSH with the
host keys its serial console shows; stop releases the external IP and start gives a new one; an
image of its disk boots a second instance at a reserved address, which it keeps across stop/start
and which cannot be released while in use; an image with nothing behind it fails the operation;
deleting everything leaves nothing. The user's path with ccrp on it is tests/scenarios.
"""

from __future__ import annotations

import io
import ipaddress
import json
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
pytest.importorskip("google.cloud.compute_v1")
paramiko = pytest.importorskip("paramiko")

from tests.contract.harness_gcp import PROJECT, REGION, ZONES



FINGERPRINTS = re.compile(r"BEGIN SSH HOST KEY FINGERPRINTS-----(.*?)-----END SSH HOST KEY FINGERPRINTS", re.DOTALL)


def _console_pins(fake, zone: str, name: str, timeout: float = 120) -> set[str]:
    """SHA256 fingerprints cloud-init printed on the serial console (the last block)."""
    deadline = time.monotonic() + timeout
    while True:
        text = fake.clients.instances.get_serial_port_output(project=PROJECT, zone=zone, instance=name).contents
        blocks = FINGERPRINTS.findall(text)
        if blocks:
            return set(re.findall(r"SHA256:([A-Za-z0-9+/]+)", blocks[-1]))
        assert time.monotonic() < deadline, f"{name}: no host key fingerprints on its console:\n{text[-2000:]}"
        time.sleep(1)


def _ssh_run(ip: str, key, pins: set[str], command: str, timeout: float = 60) -> str:
    """`command` over SSH as `tester`, the host key checked against the console's fingerprints."""
    import base64
    import hashlib

    deadline = time.monotonic() + timeout
    while True:
        transport = None
        try:
            transport = paramiko.Transport((ip, 22))
            transport.start_client(timeout=10)
            seen = base64.b64encode(hashlib.sha256(transport.get_remote_server_key().asbytes()).digest()).decode()
            assert seen.rstrip("=") in pins, f"host key SHA256:{seen} of {ip} is not on its console {pins}"
            transport.auth_publickey("tester", key)
            channel = transport.open_session(timeout=10)
            channel.exec_command(command)
            out = channel.makefile("r").read().decode()
            assert channel.recv_exit_status() == 0, f"{command}: {out}"
            return out
        except (OSError, EOFError, paramiko.SSHException) as exc:
            assert time.monotonic() < deadline, f"ssh tester@{ip}: {exc}"
            time.sleep(1)
        finally:
            if transport is not None:
                transport.close()


def test_fake_instances_boot_stop_start_capture_and_go(tmp_path):
    """compute_v1 calls only: an instance boots the debian-12 family with its metadata's user-data on
    the subnetwork's range, answers SSH on its NAT IP with the console's host keys; stop releases the
    ephemeral IP and start brings a new one; an image of its disk boots a second instance, at a
    reserved address, that keeps what the first wrote and answers at that same address after a stop
    and a start; an image without a disk here fails the insert's operation and leaves no
    instance; deletes leave no container, and deleting the image removes its Docker image."""
    if not image_buildable():
        pytest.skip(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ed25519
    from google.api_core import exceptions
    from google.cloud import compute_v1 as c

    from tests.contract.harness_gcp import PUBLIC_IMAGE
    from tests.fakes.cloudboot import CloudBoot
    from tests.fakes.gce_boot import BootingProject

    pem = ed25519.Ed25519PrivateKey.generate().private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()).decode()
    key = paramiko.Ed25519Key.from_private_key(io.StringIO(pem))
    user_data = (f"#cloud-config\nusers:\n  - name: tester\n    sudo: ALL=(ALL) NOPASSWD:ALL\n    lock_passwd: true\n"
                 f"    ssh_authorized_keys: [{key.get_name()} {key.get_base64()}]\n"
                 "write_files:\n  - path: /etc/gce-fake-marker\n    content: \"written by the first boot\\n\"\n")
    t: dict[str, float] = {}
    t0 = time.monotonic()
    with CloudBoot(progress=lambda m: None) as boot:
        fake = BootingProject(boot)
        gce = fake.clients
        cidr = fake.reserve_subnet("10.214.0.0/16")
        gce.networks.insert(project=PROJECT, network_resource=c.Network(name="net", auto_create_subnetworks=False)).result()
        gce.subnetworks.insert(project=PROJECT, region=REGION, subnetwork_resource=c.Subnetwork(
            name="sub", network="global/networks/net", ip_cidr_range=cidr, region=REGION)).result()
        debian = gce.images.get_from_family(project="debian-cloud", family="debian-12")
        assert debian.family == "debian-12" and gce.images.get(project="debian-cloud", image=debian.name).name == debian.name
        zone, host = ZONES[0], ipaddress.ip_network(cidr)

        def insert(name: str, image: str, ip_index: int, nat_ip: str | None = None):
            return gce.instances.insert(project=PROJECT, zone=zone, instance_resource=c.Instance(
                name=name, machine_type=f"zones/{zone}/machineTypes/e2-small",
                disks=[c.AttachedDisk(boot=True, auto_delete=True,
                                      initialize_params=c.AttachedDiskInitializeParams(source_image=image))],
                metadata=c.Metadata(items=[c.Items(key="user-data", value=user_data)]),
                network_interfaces=[c.NetworkInterface(subnetwork=f"regions/{REGION}/subnetworks/sub",
                                                       network_i_p=str(host.network_address + ip_index),
                                                       access_configs=[c.AccessConfig(name="nat", nat_i_p=nat_ip)])]))

        def nat(name: str) -> str:
            return gce.instances.get(project=PROJECT, zone=zone, instance=name).network_interfaces[0].access_configs[0].nat_i_p

        insert("first", f"projects/debian-cloud/global/images/family/{debian.family}", 10).result(timeout=120)
        first = gce.instances.get(project=PROJECT, zone=zone, instance="first")
        assert first.status == "RUNNING" and ipaddress.ip_address(nat("first")) in ipaddress.ip_network(fake.internet_cidr)
        pins = _console_pins(fake, zone, "first")
        # cloud-init enabled by its generator: ccrp's startup-script for debian-cloud images (kept in the
        # metadata, not run by this fake) would step aside here at once.
        out = _ssh_run(nat("first"), key, pins, "cat /etc/gce-fake-marker; ip -4 -o addr show; "
                                                "test -e /run/cloud-init/enabled && echo cloud-init-enabled")
        assert "written by the first boot" in out and f"{host.network_address + 10}/{host.prefixlen}" in out
        assert "cloud-init-enabled" in out
        t["boot + ssh"] = time.monotonic() - t0

        before = nat("first")
        gce.instances.stop(project=PROJECT, zone=zone, instance="first").result(timeout=120)
        assert gce.instances.get(project=PROJECT, zone=zone, instance="first").status == "TERMINATED" and nat("first") == ""
        gce.instances.start(project=PROJECT, zone=zone, instance="first").result(timeout=120)
        after = nat("first")
        assert after and after != before  # a new ephemeral IP
        assert "written by the first boot" in _ssh_run(after, key, pins, "cat /etc/gce-fake-marker")
        t["stop + start"] = time.monotonic() - t0 - sum(t.values())

        gce.images.insert(request=c.InsertImageRequest(project=PROJECT, force_create=True, image_resource=c.Image(
            name="snap", source_disk=first.disks[0].source))).result(timeout=300)
        snap = gce.images.get(project=PROJECT, image="snap")
        assert snap.status == "READY" and snap.archive_size_bytes > 0 and "snap" in fake.docker_images
        gce.addresses.insert(project=PROJECT, region=REGION, address_resource=c.Address(name="second-ip")).result()
        reserved = gce.addresses.get(project=PROJECT, region=REGION, address="second-ip").address
        assert ipaddress.ip_address(reserved) in ipaddress.ip_network(fake.internet_cidr)
        insert("second", f"projects/{PROJECT}/global/images/snap", 11, reserved).result(timeout=120)
        assert nat("second") == reserved
        assert gce.addresses.get(project=PROJECT, region=REGION, address="second-ip").status == "IN_USE"
        pins2 = _console_pins(fake, zone, "second")
        assert pins2 != pins  # a new instance: cloud-init made it host keys of its own
        assert "written by the first boot" in _ssh_run(reserved, key, pins2, "cat /etc/gce-fake-marker")
        t["capture + boot"] = time.monotonic() - t0 - sum(t.values())

        gce.instances.stop(project=PROJECT, zone=zone, instance="second").result(timeout=120)
        assert nat("second") == reserved  # a reserved address stays with the stopped instance
        gce.instances.start(project=PROJECT, zone=zone, instance="second").result(timeout=120)
        assert nat("second") == reserved and "written by the first boot" in _ssh_run(
            reserved, key, pins2, "cat /etc/gce-fake-marker")
        with pytest.raises(exceptions.BadRequest):  # in use by "second"
            gce.addresses.delete(project=PROJECT, region=REGION, address="second-ip")
        t["reserved stop + start"] = time.monotonic() - t0 - sum(t.values())

        with pytest.raises(exceptions.BadRequest):
            insert("ubuntu", PUBLIC_IMAGE, 12).result(timeout=60)
        with pytest.raises(exceptions.NotFound):
            gce.instances.get(project=PROJECT, zone=zone, instance="ubuntu")

        for name in ("first", "second"):
            gce.instances.delete(project=PROJECT, zone=zone, instance=name).result(timeout=120)
        gce.addresses.delete(project=PROJECT, region=REGION, address="second-ip").result()
        assert fake.addresses == {}
        ref = fake.docker_images["snap"]
        gce.images.delete(project=PROJECT, image="snap").result()
        assert fake.instances == {} and not boot.containers
        with pytest.raises(docker.errors.ImageNotFound):
            boot.client.images.get(ref)
        assert [x for x in boot.leftovers() if not x.startswith("network ")] == []
        t["delete"] = time.monotonic() - t0 - sum(t.values())
    print("timings (s):", json.dumps({k: round(v, 1) for k, v in t.items()}))
