"""ccrp gc and ccrp doctor: the leak rule, then both commands end to end on a moto server."""

from __future__ import annotations

import json

import pytest

from ccrp_cli.ops.gc import find_leaks
from ccrp_cli.models.state import FleetState, RobotRecord
from ccrp_cli.providers.base import CloneSpec, OwnedResource, Role, SnapshotRecord

from .aws_fakes import REGION

# Clones each at an Elastic IP of their own (entry: per-clone): what gc and doctor count here. Behind
# AWS's default entry gateway: test_aws_provider.py, test_quotas.py.
INVENTORY = """\
fleet: gcaws
provider: {{kind: aws, region: {region}, zones: [us-east-1a], operator_cidr: 198.51.100.0/24, entry: per-clone}}
robots:
{robots}
"""


# The roles the backends set on these kinds (AWS's and Docker's tables); gc reads only the role.
ROLES = {"vpc": Role.BOOTSTRAP, "security_group": Role.BOOTSTRAP, "key_pair": Role.BOOTSTRAP, "network": Role.BOOTSTRAP,
         "instance": Role.CLONE, "image": Role.IMAGE, "robot_sim": Role.ROBOT_SIDE}


def R(kind, rid, robot=None, name=""):
    return OwnedResource(kind=kind, id=rid, robot=robot, name=name, role=ROLES.get(kind, Role.PER_ROBOT))


def test_leak_rule():
    state = FleetState(fleet="f", snapshot={"image": "ami-current", "id": "ami-current"}, robots={
        "a": RobotRecord(index=1, phase="ready", provider_id="i-a"),
        "b": RobotRecord(index=2, phase="creating"),  # a `fleet up` died mid-create: resumable
        "c": RobotRecord(index=3, phase="planned"),
    })
    owned = [
        R("vpc", "vpc-1"), R("security_group", "sg-1"), R("key_pair", "k"), R("network", "ct-common"),
        R("instance", "i-a", "a"), R("elastic_ip", "eip-a", "a"), R("volume", "vol-a", "a"),
        R("instance", "i-a2", "a"),  # a second instance for a: not the one state knows
        R("instance", "i-b", "b"), R("elastic_ip", "eip-b", "b"),
        R("instance", "i-c", "c"), R("elastic_ip", "eip-c", "c"),  # c has no clone in state
        R("elastic_ip", "eip-ghost", "ghost"),
        R("image", "ami-current"), R("image", "ami-kept", "a"), R("image", "ami-lost"),
        R("snapshot", "snap-orphan"), R("robot_sim", "sim-a", "a"), R("robot_sim", "sim-z", "z"),
    ]
    snapshots = [SnapshotRecord(id="ami-kept", name="kept", created="", source="a")]
    assert [r.id for r in find_leaks(state, owned, snapshots)] == [
        "i-a2", "i-c", "eip-c", "eip-ghost", "ami-lost", "snap-orphan", "sim-z"]


def write_inventory(tmp_path, robots: int):
    path = tmp_path / "aws.yaml"
    path.write_text(INVENTORY.format(region=REGION, robots="\n".join(f"  - name: robot{i}" for i in range(1, robots + 1))))
    return path


@pytest.fixture
def fleet_on_moto(moto_url, ccrp_home, tmp_path):
    """Fleet gcaws bootstrapped on the moto server, robot1's clone recorded in state."""
    import boto3

    from ccrp_cli.fleet import Fleet
    from ccrp_cli.providers import get_provider

    path = write_inventory(tmp_path, 2)
    fleet = Fleet.open(path)
    provider = get_provider(fleet.inventory)
    provider.bootstrap()
    ec2 = boto3.client("ec2", region_name=REGION)
    image = ec2.register_image(Name="base", RootDeviceName="/dev/sda1", Architecture="x86_64")["ImageId"]
    rec = provider.run_instance(CloneSpec(robot="robot1", hostname="cri-robot1", image=image, user_data="#cloud-config\n{}\n",
                                          instance_id="gcaws-robot1-1", common_ip="10.90.0.10", vpn_subnet="10.80.1.0/24"))
    with fleet.store.lock():
        state = fleet.load_allocated()
        state.robots["robot1"].phase, state.robots["robot1"].provider_id = "ready", rec.provider_id
        fleet.store.save_state(state)
    return path, ec2, rec.provider_id, image


def _tags(robot):
    labels = {"ccrp-managed": "true", "ccrp-fleet": "gcaws", "ccrp-role": "clone", "ccrp-robot": robot}
    return [{"Key": k, "Value": v} for k, v in labels.items()]


def test_gc_cli_lists_then_deletes_leaks(fleet_on_moto, ccrp):
    path, ec2, clone, image = fleet_on_moto
    # A clone for robot2 that state never recorded, and an Elastic IP of a robot long gone.
    leak_vm = ec2.run_instances(ImageId=image, MinCount=1, MaxCount=1, TagSpecifications=[
        {"ResourceType": "instance", "Tags": _tags("robot2")}])["Instances"][0]["InstanceId"]
    leak_ip = ec2.allocate_address(Domain="vpc", TagSpecifications=[
        {"ResourceType": "elastic-ip", "Tags": _tags("old")}])["AllocationId"]
    foreign = ec2.allocate_address(Domain="vpc")["AllocationId"]  # no tags: never ccrp's business

    dry = ccrp("gc", "-i", str(path), "--dry-run", "--json", check=True)
    listed = json.loads(dry.stdout)
    assert {(r["kind"], r["id"], r["action"]) for r in listed} == {("instance", leak_vm, "leak"), ("elastic_ip", leak_ip, "leak")}
    assert ec2.describe_addresses(AllocationIds=[leak_ip])["Addresses"]  # dry run deleted nothing

    done = json.loads(ccrp("gc", "-i", str(path), "--json", check=True).stdout)
    assert {(r["id"], r["action"]) for r in done} == {(leak_vm, "deleted"), (leak_ip, "deleted")}
    state = {i["InstanceId"]: i["State"]["Name"] for r in ec2.describe_instances()["Reservations"] for i in r["Instances"]}
    assert state[leak_vm] in ("shutting-down", "terminated") and state[clone] == "running"
    left = {a["AllocationId"] for a in ec2.describe_addresses()["Addresses"]}
    assert leak_ip not in left and foreign in left
    assert json.loads(ccrp("gc", "-i", str(path), "--json", check=True).stdout) == []
    human = ccrp("gc", "-i", str(path), "--dry-run", check=True)
    assert "0 leaked resources" in human.stderr


def test_doctor_cli_on_moto(fleet_on_moto, ccrp, ccrp_home):
    path, ec2, clone, image = fleet_on_moto
    proc = ccrp("doctor", "-i", str(path), "--json")
    rows = {r["check"]: r for r in json.loads(proc.stdout)}
    assert proc.returncode == 1  # no snapshot recorded yet
    assert rows["sdk boto3"]["status"] == "ok" and rows["credentials"]["status"] == "ok"
    assert rows["aws client"] == {"check": "aws client", "status": "ok", "detail": "region/cloud us-east-1", "hint": ""}
    assert "123456789012" in rows["credentials"]["detail"]  # moto's account
    eips = "quota EC2-VPC Elastic IPs in region us-east-1"
    assert rows[eips]["status"] == "ok"
    assert rows[eips]["detail"] == "limit 5, used 1; the fleet's 1 clone(s) not created yet need 1"
    assert rows["snapshot"]["status"] == "fail" and "snapshot bake" in rows["snapshot"]["hint"]

    from ccrp_cli.fleet import Fleet

    fleet = Fleet.open(path)
    state = fleet.store.load_state()
    state.snapshot = {"image": image, "id": image, "source": "build"}
    fleet.store.save_state(state)
    proc = ccrp("doctor", "-i", str(path), "--json")
    rows = {r["check"]: r for r in json.loads(proc.stdout)}
    assert rows["snapshot"] == {"check": "snapshot", "status": "ok", "detail": image, "hint": ""}
    assert proc.returncode == 0, proc.stdout

    # Six clones need six Elastic IPs; the account (moto's default, like AWS's) allows five, and
    # robot1's clone holds one of them already.
    (path.parent / "big").mkdir()
    big = write_inventory(path.parent / "big", 6)
    proc = ccrp("doctor", "-i", str(big), "--json")
    rows = {r["check"]: r for r in json.loads(proc.stdout)}
    assert rows[eips]["status"] == "fail" and proc.returncode == 1
    assert rows[eips]["detail"] == "limit 5, used 1; the fleet's 5 clone(s) not created yet need 5"
    assert "L-0263D0A3" in rows[eips]["hint"]


def test_doctor_unknown_profile_is_a_failed_row(aws_env, ccrp, tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(write_inventory(tmp_path, 1).read_text().replace("kind: aws,", "kind: aws, profile: nosuch,"))
    proc = ccrp("doctor", "-i", str(path))
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert "nosuch" in proc.stdout and "aws configure" in proc.stdout


def test_gc_without_state_refuses_to_delete(moto_url, ccrp, tmp_path):
    import boto3

    path = write_inventory(tmp_path, 1)
    ec2 = boto3.client("ec2", region_name=REGION)
    owned = ec2.allocate_address(Domain="vpc", TagSpecifications=[{"ResourceType": "elastic-ip", "Tags": _tags("robot1")}])
    proc = ccrp("gc", "-i", str(path))
    assert proc.returncode == 1 and "no state for fleet 'gcaws'" in proc.stderr
    assert ec2.describe_addresses(AllocationIds=[owned["AllocationId"]])["Addresses"]
    assert len(json.loads(ccrp("gc", "-i", str(path), "--dry-run", "--json", check=True).stdout)) == 1


def test_doctor_reaching_the_docker_engine_is_its_credential(ccrp_home, monkeypatch):
    """Docker declares it (ProviderInfo.reach, reach_is_credential): doctor's row names the engine
    and says its version, and no credentials row follows."""
    from types import SimpleNamespace

    from ccrp_cli import providers
    from ccrp_cli.fleet import Fleet
    from ccrp_cli.ops import doctor
    from tests.conftest import LAB

    engine = SimpleNamespace(kind="docker", check_credentials=lambda: "Docker 27.0 (API 1.47)")
    monkeypatch.setattr(providers, "get_provider", lambda inv: engine)
    provider, row = doctor._provider(Fleet.open(LAB))
    assert provider is engine and row == doctor.Check("docker engine", doctor.OK, "Docker 27.0 (API 1.47)")
    assert doctor._credentials(engine) == []
