"""The EC2 fake whose instances really boot (tests/fakes/aws_boot.py), driven with plain boto3 and
no ccrp in between: gzipped user-data runs, the Elastic IP answers SSH, stop/start act on the
instance, a captured AMI boots, an unknown AMI is refused, and the injected faults come back as
the errors ccrp classifies. The user's path with ccrp on it is tests/scenarios.
"""

from __future__ import annotations

import ipaddress
import time

import pytest

from tests.fakes.cloudboot import DEBIAN_12, docker_available, image_buildable

NO_DOCKER = docker_available()

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(NO_DOCKER is not None, reason=f"needs a running Docker engine ({NO_DOCKER})"),
]

docker = pytest.importorskip("docker")
pytest.importorskip("boto3")
pytest.importorskip("moto.server")
pytest.importorskip("paramiko")

from tests.scenarios.backend_aws import open_backend



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

    if not image_buildable():
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

        def launch(image: str, host: int, user_data: bytes = b"", leg: str | None = None) -> str:
            first = {"DeviceIndex": 0, "SubnetId": subnet, "PrivateIpAddress": str(cidr[host])}
            legs = [first, {"DeviceIndex": 1, "SubnetId": leg}] if leg else [first | {"AssociatePublicIpAddress": False}]
            iid = ec2.run_instances(ImageId=image, MinCount=1, MaxCount=1, UserData=user_data,
                                    NetworkInterfaces=legs)["Instances"][0]["InstanceId"]
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
        # Two interfaces (an entry gateway's), in two subnets: the container has a leg on each one's network.
        other = yaml.safe_load(backend.inventory.read_text())["provider"]["gateway_cidr"]
        ec2.associate_vpc_cidr_block(VpcId=vpc, CidrBlock=other)
        leg = ec2.create_subnet(VpcId=vpc, CidrBlock=other, AvailabilityZone="us-east-1b")["Subnet"]["SubnetId"]
        second = launch(ami, 21, leg=leg)
        assert fake.boot.client.containers.get(fake.boot.containers[second].id).image.tags[0] == fake.disks[ami]
        nics = ec2.describe_instances(InstanceIds=[second])["Reservations"][0]["Instances"][0]["NetworkInterfaces"]
        assert sorted(fake.boot.attachments(second).values()) == sorted(n["PrivateIpAddress"] for n in nics)
        assert len(nics) == 2 and str(cidr[21]) in fake.boot.attachments(second).values()
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
