"""The user's path on AWS, through `ccrp` run as a separate process exactly as typed, against moto
whose EC2 instances really boot (tests/fakes/aws_boot.py, scenarios/backend_aws.py):

vpn init; snapshot bake (no image named: ccrp resolves Debian 12 from the public SSM parameter, a
builder instance boots it and installs the recipe with cloud-init from Debian's mirror and PyPI,
then CreateImage captures it); clone create for nao1 (the clone boots from that AMI, gets its
Elastic IP, SSH pinned from the console output, secrets pushed); status --json shows it running
with its master reachable; clone exec; fleet down; gc --dry-run finds nothing; moto holds nothing
tagged with the fleet; no instance container is left, and the backend's exit removes every
container, network and image of the run.

The bake installs packages from the internet: about two minutes here. Timings are printed
(pytest -s shows them).
"""

from __future__ import annotations

import ipaddress
import json
import shutil
import time

import pytest

from tests.fakes.cloudboot import DEBIAN_12, docker_available

_NO_DOCKER = docker_available()

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(_NO_DOCKER is not None, reason=f"needs a running Docker engine ({_NO_DOCKER})"),
]

docker = pytest.importorskip("docker")
pytest.importorskip("boto3")
pytest.importorskip("moto.server")
pytest.importorskip("paramiko")

from tests.scenarios.backend_aws import open_backend

FLEET = "awsboot"


def _image_buildable() -> bool:
    if shutil.which("mmdebstrap"):
        return True
    try:
        with docker.from_env(timeout=30) as client:
            client.images.get(DEBIAN_12)
        return True
    except docker.errors.DockerException:
        return False


def test_user_path_on_a_booting_ec2(tmp_path):
    if not _image_buildable():
        pytest.skip(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it")
    timings: dict[str, float] = {}
    t_start = time.monotonic()

    with open_backend(tmp_path, FLEET) as backend:
        fake = backend.fake
        inv = str(backend.inventory)
        assert "profile" not in backend.inventory.read_text() and "image" not in backend.inventory.read_text()

        def ccrp(step: str, *args: str, timeout: float = 900):
            t0 = time.monotonic()
            proc = backend.ccrp(*args, timeout=timeout)
            timings[step] = round(time.monotonic() - t0, 1)
            assert "Traceback" not in proc.stderr, proc.stderr[-3000:]
            assert proc.returncode == 0, (f"ccrp {' '.join(args)} exited {proc.returncode}\n"
                                          f"stderr: {proc.stderr[-3000:]}\nstdout: {proc.stdout[-2000:]}\n"
                                          f"fake errors: {fake.errors}")
            return proc

        try:
            ccrp("vpn init", "vpn", "init", "-i", inv)
            ccrp("snapshot bake", "snapshot", "bake", "-i", inv, timeout=1800)
            snaps = json.loads(ccrp("snapshot list", "snapshot", "list", "-i", inv, "--json").stdout)
            assert len(snaps) == 1 and snaps[0]["id"] in fake.captured, (snaps, fake.captured)
            # The builder booted the Debian 12 AMI the SSM parameter names, and is gone.
            assert fake.calls["ssm GetParameter"] >= 1

            ccrp("clone create nao1", "clone", "create", "-i", inv, "--robot", "nao1")
            rows = {r["robot"]: r for r in json.loads(ccrp("status", "status", "-i", inv, "--json").stdout)}
            nao1 = rows["nao1"]
            assert nao1["status"] == "running" and nao1["phase"] == "ready", nao1
            assert nao1["master_reachable"] is True and nao1["secrets"] is True, nao1
            assert ipaddress.IPv4Address(nao1["public_ip"]) in ipaddress.IPv4Network(fake.internet_cidr), nao1
            assert rows["nao2"]["status"] == "absent", rows["nao2"]
            out = ccrp("clone exec", "clone", "exec", "-i", inv, "--robot", "nao1", "--", "hostname").stdout
            assert out.strip() == "cri-nao1", out
            running = [c for c in fake.boot.leftovers() if c.startswith("container ")]
            assert len(running) == 1, running  # the clone; the builder was terminated

            ccrp("fleet down", "fleet", "down", "-i", inv)
            leaked = json.loads(ccrp("gc --dry-run", "gc", "-i", inv, "--dry-run", "--json").stdout)
            assert leaked == [], leaked
            assert backend.owned() == [], backend.owned()
            fake.wait_idle()
            assert [c for c in fake.boot.leftovers() if c.startswith("container ")] == []
            assert fake.errors == {}, fake.errors
        finally:
            print(f"\nAWS user path timings (s): {timings}; EC2 calls: {sum(fake.calls.values())}")
        boot = fake.boot
    assert boot.leftovers() == [], boot.leftovers()
    print(f"total {time.monotonic() - t_start:.1f} s (fake's start and cleanup included)")


def test_fake_instances_boot_stop_start_capture_and_faults(tmp_path):
    """The fake itself through plain boto3 (no ccrp): gzip user-data reaches cloud-init, the Elastic
    IP answers on port 22 from this host, the console is EC2's base64 (botocore decodes it), stop and
    start act on the container, an AMI from CreateImage boots; faults come as EC2 sends them and
    ccrp classifies them as throttling, quota and zone errors."""
    import gzip
    import socket

    from botocore.config import Config
    from botocore.exceptions import ClientError

    from ccrp_cli.providers.aws.errors import classify
    from ccrp_cli.retry import ErrorClass
    from tests.fakes.aws_boot import DEBIAN_SSM

    if not _image_buildable():
        pytest.skip(f"{DEBIAN_12} is missing and mmdebstrap is not installed to build it")
    with open_backend(tmp_path, "awsfake") as backend:
        fake = backend.fake
        ec2, ssm = fake.client(), fake.client("ssm")
        assert ssm.get_parameter(Name=DEBIAN_SSM)["Parameter"]["Value"] == fake.debian_ami
        import yaml

        cidr = ipaddress.IPv4Network(yaml.safe_load(backend.inventory.read_text())["common"]["cidr"])
        vpc = ec2.create_vpc(CidrBlock=str(cidr))["Vpc"]["VpcId"]
        subnet = ec2.create_subnet(VpcId=vpc, CidrBlock=str(cidr), AvailabilityZone="us-east-1b")["Subnet"]["SubnetId"]
        wait = {"Delay": 1, "MaxAttempts": 120}

        def launch(image: str, host: int, user_data: bytes = b"") -> str:
            iid = ec2.run_instances(ImageId=image, MinCount=1, MaxCount=1, UserData=user_data, NetworkInterfaces=[
                {"DeviceIndex": 0, "SubnetId": subnet, "PrivateIpAddress": str(cidr[host]),
                 "AssociatePublicIpAddress": False}])["Instances"][0]["InstanceId"]
            ec2.get_waiter("instance_running").wait(InstanceIds=[iid], WaiterConfig=wait)
            return iid

        def console_until(iid: str, *needles: str) -> str:
            for _ in range(90):
                out = ec2.get_console_output(InstanceId=iid).get("Output", "")
                if all(n in out for n in needles):
                    return out
                time.sleep(1)
            raise AssertionError(f"console of {iid} never showed {needles}: {out[-1500:]}")

        marker = "hello-from-gzipped-user-data"
        ud = f"#cloud-config\nruncmd:\n  - [sh, -c, 'echo {marker} > /dev/console']\n".encode()
        iid = launch(fake.debian_ami, 20, gzip.compress(ud))
        eip = ec2.allocate_address(Domain="vpc")
        assert ipaddress.IPv4Address(eip["PublicIp"]) in ipaddress.IPv4Network(fake.internet_cidr)
        ec2.associate_address(AllocationId=eip["AllocationId"], InstanceId=iid)
        console_until(iid, marker, "END SSH HOST KEY FINGERPRINTS")
        socket.create_connection((eip["PublicIp"], 22), timeout=10).close()

        ami = ec2.create_image(InstanceId=iid, Name="captured")["ImageId"]
        ec2.get_waiter("image_available").wait(ImageIds=[ami], WaiterConfig=wait)
        ec2.stop_instances(InstanceIds=[iid])
        ec2.get_waiter("instance_stopped").wait(InstanceIds=[iid], WaiterConfig=wait)
        assert fake.boot.state(iid) == "exited"
        ec2.start_instances(InstanceIds=[iid])
        ec2.get_waiter("instance_running").wait(InstanceIds=[iid], WaiterConfig=wait)
        assert fake.boot.state(iid) == "running"
        second = launch(ami, 21)
        assert fake.boot.client.containers.get(fake.boot.containers[second].id).image.tags[0] == fake.disks[ami]
        console_until(second, "END SSH HOST KEY FINGERPRINTS")

        with pytest.raises(ClientError) as unknown:
            ec2.run_instances(ImageId="ami-0123456789abcdef0", MinCount=1, MaxCount=1)
        assert unknown.value.response["Error"]["Code"] == "InvalidAMIID.NotFound"

        import boto3

        # A client as ccrp builds it (no retries of its own, no bypass header): the faults reach it.
        plain = boto3.session.Session().client("ec2", region_name=fake.region, endpoint_url=fake.url,
                                               aws_access_key_id="testing", aws_secret_access_key="testing",
                                               config=Config(retries={"total_max_attempts": 1}))

        def error(fn, **kwargs) -> ClientError:
            with pytest.raises(ClientError) as exc:
                fn(**kwargs)
            return exc.value

        with backend.faults["storm"](0.5):
            codes = []
            for _ in range(4):
                try:
                    plain.describe_vpcs()
                    codes.append("ok")
                except ClientError as exc:
                    codes.append(exc.response["Error"]["Code"])
                    assert classify(exc) is ErrorClass.RETRYABLE
        assert codes.count("RequestLimitExceeded") == 2, codes
        run = {"ImageId": fake.debian_ami, "MinCount": 1, "MaxCount": 1, "NetworkInterfaces": [
            {"DeviceIndex": 0, "SubnetId": subnet, "AssociatePublicIpAddress": False}]}
        with backend.faults["quota"]():
            exc = error(plain.run_instances, **run)
            assert exc.response["Error"]["Code"] == "InstanceLimitExceeded" and classify(exc) is ErrorClass.REGION
        with backend.faults["zone"]("us-east-1b"):
            exc = error(plain.run_instances, **run)
            assert exc.response["Error"]["Code"] == "InsufficientInstanceCapacity" and classify(exc) is ErrorClass.ZONE
            exc = error(plain.create_subnet, VpcId=vpc, CidrBlock=str(cidr), AvailabilityZone="us-east-1b")
            assert classify(exc) is ErrorClass.ZONE, exc.response

        ec2.terminate_instances(InstanceIds=[iid, second])
        ec2.get_waiter("instance_terminated").wait(InstanceIds=[iid, second], WaiterConfig=wait)
        assert not fake.boot.has(iid) and not fake.boot.has(second)
        assert fake.errors == {}, fake.errors
        boot = fake.boot
    assert boot.leftovers() == [], boot.leftovers()
