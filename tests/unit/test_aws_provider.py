"""What the AWS provider does beyond the shared contract: error classes, the security group
converging to exactly the public rules, an existing VPC left alone, gzip of large user-data,
zone fallback for the common subnet; both layouts: clones at their own Elastic IPs (entry:
per-clone) and behind the fleet's entry gateway (AWS's default)."""

from __future__ import annotations

import base64
import gzip

import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.providers.base import Origin
from ccrp_cli.retry import ErrorClass
from tests.contract import specs
from tests.contract.specs import FAST, clone_spec, inventory

from .aws_fakes import REGION, inject_error

PROVIDER = {"kind": "aws", "region": REGION, "zones": ["us-east-1a", "us-east-1b"], "operator_cidr": "198.51.100.0/24"}
PER_CLONE = {"entry": "per-clone"}


@pytest.fixture
def mocked(aws_env):
    from moto import mock_aws

    with mock_aws():
        yield


def make(tmp_path, bootstrap: bool = True, **settings):
    from ccrp_cli.providers.aws.provider import AwsProvider

    p = AwsProvider(inventory(PROVIDER | settings), tmp_path / "store")
    p.client.backoff = FAST
    if bootstrap:
        p.bootstrap()
    return p


def image(p) -> str:
    return p.client.ec2.register_image(Name="base", RootDeviceName="/dev/sda1", Architecture="x86_64")["ImageId"]


@pytest.mark.parametrize("code,status,expected", [
    ("RequestLimitExceeded", 503, ErrorClass.RETRYABLE),
    ("Throttling", 400, ErrorClass.RETRYABLE),
    ("InternalError", 500, ErrorClass.RETRYABLE),
    ("SomethingNew", 502, ErrorClass.RETRYABLE),
    ("InsufficientInstanceCapacity", 500, ErrorClass.ZONE),
    ("InstanceLimitExceeded", 400, ErrorClass.REGION),
    ("VcpuLimitExceeded", 400, ErrorClass.REGION),
    ("InvalidAMIID.NotFound", 400, ErrorClass.FATAL),
    ("UnauthorizedOperation", 403, ErrorClass.FATAL),
])
def test_classify(code, status, expected):
    from botocore.exceptions import ClientError, EndpointConnectionError

    from ccrp_cli.providers.aws.errors import as_ccrp, classify

    exc = ClientError({"Error": {"Code": code, "Message": "m"}, "ResponseMetadata": {"HTTPStatusCode": status}}, "RunInstances")
    assert classify(exc) is expected
    assert classify(as_ccrp("launch", exc)) is expected  # the one-line error keeps its class
    assert classify(EndpointConnectionError(endpoint_url="https://ec2")) is ErrorClass.RETRYABLE
    from botocore.parsers import ResponseParserError

    assert classify(ResponseParserError("Unable to parse response (syntax error), invalid XML received: <html>")) is ErrorClass.RETRYABLE


def test_unsupported_zone_is_a_zone_error():
    from botocore.exceptions import ClientError

    from ccrp_cli.providers.aws.errors import classify

    msg = "Your requested instance type is not supported in your requested Availability Zone (us-east-1e)."
    exc = ClientError({"Error": {"Code": "Unsupported", "Message": msg}}, "RunInstances")
    assert classify(exc) is ErrorClass.ZONE
    assert classify(ClientError({"Error": {"Code": "Unsupported", "Message": "other"}}, "X")) is ErrorClass.FATAL


def test_bootstrap_converges_security_group_and_is_idempotent(mocked, tmp_path):
    p = make(tmp_path, **PER_CLONE)
    net = p.network
    # Someone opens the ROS master to the world by hand: the next bootstrap closes it.
    p.client.ec2.authorize_security_group_ingress(GroupId=net.security_group_id, IpPermissions=[
        {"IpProtocol": "tcp", "FromPort": 11311, "ToPort": 11311, "IpRanges": [{"CidrIp": "0.0.0.0/0"}]}])
    p.bootstrap()
    from ccrp_cli.providers.aws import network

    sg = p.client.ec2.describe_security_groups(GroupIds=[net.security_group_id])["SecurityGroups"][0]
    assert {(r[0], r[1], r[3]) for r in network.ingress_rules(sg)} == {
        ("udp", 1194, "0.0.0.0/0"), ("tcp", 22, "198.51.100.0/24"), ("-1", -1, "10.90.0.0/24")}
    assert p.network == net
    assert len(p.client.ec2.describe_vpcs(Filters=[{"Name": "tag:ccrp-fleet", "Values": ["ct"]}])["Vpcs"]) == 1
    key = p.client.ec2.describe_key_pairs(KeyNames=["ccrp-ct"], IncludePublicKey=True)["KeyPairs"][0]
    assert key["PublicKey"].split()[:2] == p.operator_public_key().split()[:2]


def test_existing_vpc_is_used_and_left_alone(mocked, tmp_path):
    import boto3

    ec2 = boto3.client("ec2", region_name=REGION)
    vpc = ec2.create_vpc(CidrBlock="10.90.0.0/16")["Vpc"]["VpcId"]
    igw = ec2.create_internet_gateway()["InternetGateway"]["InternetGatewayId"]
    ec2.attach_internet_gateway(InternetGatewayId=igw, VpcId=vpc)
    p = make(tmp_path, vpc_id=vpc)
    assert p.network.vpc_id == vpc
    removed = p.teardown()
    assert any(r.startswith("subnet") for r in removed) and not any(r.startswith(("vpc", "internet_gateway")) for r in removed)
    assert ec2.describe_vpcs(VpcIds=[vpc])["Vpcs"]
    assert ec2.describe_internet_gateways(InternetGatewayIds=[igw])["InternetGateways"][0]["Attachments"]


def test_vpc_without_internet_gateway_is_refused(mocked, tmp_path):
    import boto3

    vpc = boto3.client("ec2", region_name=REGION).create_vpc(CidrBlock="10.90.0.0/16")["Vpc"]["VpcId"]
    with pytest.raises(CcrpError, match="no internet gateway"):
        make(tmp_path, vpc_id=vpc)


def test_common_subnet_falls_back_to_the_next_zone(mocked, tmp_path):
    p = make(tmp_path, bootstrap=False)
    inject_error(p.client.ec2, "CreateSubnet", "Unsupported",
                 "The requested Availability Zone us-east-1a is currently constrained",
                 when=lambda body: body.get("AvailabilityZone") == "us-east-1a")
    p.bootstrap()
    assert p.network.zone == "us-east-1b"


def test_large_user_data_is_gzipped_within_the_limit(mocked, tmp_path):
    p = make(tmp_path)
    spec = clone_spec(p.inv, "robot1", 1, image(p))
    spec.user_data += "".join(f"# padding line {i}: the same words again and again\n" for i in range(600))
    assert len(spec.user_data.encode()) > 16_384
    rec = p.run_instance(spec)
    sent = base64.b64decode(p.client.ec2.describe_instance_attribute(InstanceId=rec.provider_id, Attribute="userData")["UserData"]["Value"])
    assert len(sent) <= 16_384 and gzip.decompress(sent).decode() == spec.user_data


def test_capacity_error_at_launch_leaves_nothing(mocked, tmp_path):
    p = make(tmp_path)
    inject_error(p.client.ec2, "RunInstances", "InsufficientInstanceCapacity", "We currently do not have sufficient t3.medium capacity")
    with pytest.raises(CcrpError) as err:
        p.run_instance(clone_spec(p.inv, "robot1", 1, image(p)))
    assert "capacity" in err.value.one_line() and "instance_type" in (err.value.hint or "")
    assert p.query() == {} and not p.client.ec2.describe_addresses()["Addresses"]


def test_throttling_gives_up_with_one_line(mocked, tmp_path):
    p = make(tmp_path)
    for _ in range(FAST.attempts):
        inject_error(p.client.ec2, "DescribeInstances", "RequestLimitExceeded", "Request limit exceeded.", status=503)
    with pytest.raises(CcrpError, match=f"still failing after {FAST.attempts} attempts"):
        p.query()


def test_clone_route_and_source_dest_check(mocked, tmp_path):
    p = make(tmp_path, **PER_CLONE)
    rec = p.run_instance(clone_spec(p.inv, "robot2", 2, image(p)))
    rt = p.client.ec2.describe_route_tables(RouteTableIds=[p.network.route_table_id])["RouteTables"][0]
    assert {"10.80.2.0/24": rec.provider_id} == {r["DestinationCidrBlock"]: r["InstanceId"] for r in rt["Routes"] if r.get("InstanceId")}
    attr = p.client.ec2.describe_instance_attribute(InstanceId=rec.provider_id, Attribute="sourceDestCheck")
    assert attr["SourceDestCheck"]["Value"] is False
    assert rec.common_ip == "10.90.0.11" and rec.public_ip
    p.terminate("robot2")
    rt = p.client.ec2.describe_route_tables(RouteTableIds=[p.network.route_table_id])["RouteTables"][0]
    assert not [r for r in rt["Routes"] if r.get("InstanceId")]


def test_console_output_falls_back_when_latest_is_unsupported(mocked, tmp_path):
    p = make(tmp_path)
    p.run_instance(clone_spec(p.inv, "robot1", 1, image(p)))
    inject_error(p.client.ec2, "GetConsoleOutput", "UnsupportedOperation", "Latest is only supported on Nitro instances",
                 when=lambda body: body.get("Latest") in ("true", True))
    assert "Linux version" in p.console_output("robot1")  # moto's console text, decoded from base64
    with pytest.raises(CcrpError, match="no clone"):
        p.console_output("robot2")


DEBIAN_12 = "/aws/service/debian/release/bookworm/latest/amd64"


def _publish(name: str, ami: str) -> None:
    """A public parameter as AWS publishes it (moto refuses /aws/ names from put_parameter, so it goes
    into moto's store the way moto loads AWS's own public parameters)."""
    import time

    from moto.core import DEFAULT_ACCOUNT_ID
    from moto.ssm.models import Parameter, ssm_backends

    ssm_backends[DEFAULT_ACCOUNT_ID][REGION]._parameters[name].append(Parameter(
        account_id=DEFAULT_ACCOUNT_ID, name=name, value=ami, parameter_type="String", description=None,
        allowed_pattern=None, keyid=None, last_modified_date=time.time(), version=1, data_type="aws:ec2:image"))


def test_debians_ssm_parameter_resolves_to_the_ami_it_names(mocked, tmp_path):
    from ccrp_cli.providers import info

    p = make(tmp_path, bootstrap=False)
    ami = image(p)
    _publish(DEBIAN_12, ami)
    assert info("aws").bake_base == DEBIAN_12
    assert p.resolve_image(DEBIAN_12) == ami
    assert p.resolve_image(f"resolve:ssm:{DEBIAN_12}") == ami  # EC2's own spelling of the same
    assert p.resolve_image(ami) == ami and p.has_image(ami)
    with pytest.raises(CcrpError, match=r"^AWS get SSM parameter /aws/service/debian/release/trixie/latest/amd64: .*not found") as err:
        p.resolve_image("/aws/service/debian/release/trixie/latest/amd64")
    assert "\n" not in err.value.one_line()


# -- the entry gateway (provider.entry: gateway, AWS's default) -------------------------------------

def gateway_spec(p, img: str):
    return specs.gateway_spec(p.inv, clone_spec(p.inv, "robot1", 1, img))


def default_route(p, rt_id: str) -> dict:
    rt = p.client.ec2.describe_route_tables(RouteTableIds=[rt_id])["RouteTables"][0]
    return next(r for r in rt["Routes"] if r.get("DestinationCidrBlock") == "0.0.0.0/0")


def test_the_gateway_holds_the_fleets_one_address_on_a_public_leg_and_is_the_clones_way_out(mocked, tmp_path):
    """Its first interface in its own public subnet (routed to the internet gateway) with its own
    group (the robots' ports, SSH from the operator) and the fleet's Elastic IP; its second at
    gateway_ip in the clones' subnet, whose default route leads to it; source/dest check off on
    both. Clones: no address, a group open only to the common network. Made again, the gateway
    has the same address and the clones' route follows its new interface."""
    from ccrp_cli.models.addressing import capacity
    from ccrp_cli.providers.aws import network

    p = make(tmp_path)
    ec2, net, img = p.client.ec2, p.network, image(p)
    assert net.gateway_subnet_id and net.gateway_group_id
    gw_subnet = ec2.describe_subnets(SubnetIds=[net.gateway_subnet_id])["Subnets"][0]
    assert gw_subnet["CidrBlock"] == "100.64.0.0/28" and gw_subnet["AvailabilityZone"] == net.zone
    igw = ec2.describe_internet_gateways(Filters=[{"Name": "attachment.vpc-id", "Values": [net.vpc_id]}])["InternetGateways"][0]
    public_rt = ec2.describe_route_tables(Filters=[{"Name": "association.subnet-id", "Values": [net.gateway_subnet_id]}])["RouteTables"][0]
    assert default_route(p, public_rt["RouteTableId"])["GatewayId"] == igw["InternetGatewayId"]
    groups = {g["GroupId"]: network.ingress_rules(g) for g in ec2.describe_security_groups(
        GroupIds=[net.security_group_id, net.gateway_group_id])["SecurityGroups"]}
    assert groups[net.gateway_group_id] == {("udp", 1195, 1194 + capacity(p.inv), "0.0.0.0/0"),
                                            ("tcp", 22, 22, "198.51.100.0/24")}
    assert groups[net.security_group_id] == {("-1", -1, -1, "10.90.0.0/24")}

    gw = p.run_instance(gateway_spec(p, img))
    assert p.gateway() is not None and p.gateway().provider_id == gw.provider_id
    assert gw.public_ip and gw.common_ip == "10.90.0.8" and p.ssh_address(gw) == gw.public_ip
    inst = ec2.describe_instances(InstanceIds=[gw.provider_id])["Reservations"][0]["Instances"][0]
    assert inst["InstanceType"] == "t3.micro"
    legs = {n["Attachment"]["DeviceIndex"]: n for n in inst["NetworkInterfaces"]}
    assert legs[0]["SubnetId"] == net.gateway_subnet_id and [g["GroupId"] for g in legs[0]["Groups"]] == [net.gateway_group_id]
    assert legs[1]["SubnetId"] == net.subnet_id and legs[1]["PrivateIpAddress"] == "10.90.0.8"
    for leg in legs.values():
        attr = ec2.describe_network_interface_attribute(NetworkInterfaceId=leg["NetworkInterfaceId"], Attribute="sourceDestCheck")
        assert attr["SourceDestCheck"]["Value"] is False
    [eip] = ec2.describe_addresses()["Addresses"]
    assert eip["PublicIp"] == gw.public_ip and eip["NetworkInterfaceId"] == legs[0]["NetworkInterfaceId"]
    assert default_route(p, net.route_table_id)["NetworkInterfaceId"] == legs[1]["NetworkInterfaceId"]

    clone = p.run_instance(clone_spec(p.inv, "robot2", 2, img))
    assert clone.public_ip is None and clone.common_ip == "10.90.0.11" and p.behind_gateway(clone)
    assert len(ec2.describe_addresses()["Addresses"]) == 1

    ec2.terminate_instances(InstanceIds=[gw.provider_id])  # an operator, a failure
    assert p.gateway() is None
    again = p.run_instance(gateway_spec(p, img))
    assert again.provider_id != gw.provider_id and again.public_ip == gw.public_ip
    inst = ec2.describe_instances(InstanceIds=[again.provider_id])["Reservations"][0]["Instances"][0]
    leg = next(n for n in inst["NetworkInterfaces"] if n["Attachment"]["DeviceIndex"] == 1)
    assert default_route(p, net.route_table_id)["NetworkInterfaceId"] == leg["NetworkInterfaceId"]


def test_a_kept_clone_behind_a_new_gateway_gives_its_elastic_ip_back(mocked, tmp_path):
    p = make(tmp_path, **PER_CLONE)
    img = image(p)
    rec = p.run_instance(clone_spec(p.inv, "robot1", 1, img))
    assert rec.public_ip and len(p.client.ec2.describe_addresses()["Addresses"]) == 1
    gw = make(tmp_path)  # the same fleet, now behind a gateway (AWS's default)
    again = gw.run_instance(clone_spec(gw.inv, "robot1", 1, img))
    assert again.provider_id == rec.provider_id and again.public_ip is None
    assert gw.client.ec2.describe_addresses()["Addresses"] == []
    # and back: per-clone again, the clones' default route is the internet gateway's again
    gw.run_instance(gateway_spec(gw, img))
    back = make(tmp_path, **PER_CLONE)
    assert default_route(back, back.network.route_table_id).get("GatewayId", "").startswith("igw-")


def test_the_gateway_is_gateway_to_gc_and_fleet_down_leaves_nothing(mocked, tmp_path):
    from ccrp_cli.providers.aws import owned
    from ccrp_cli.providers.base import GATEWAY, Role

    p = make(tmp_path)
    img = image(p)
    p.run_instance(gateway_spec(p, img))
    p.run_instance(clone_spec(p.inv, "robot2", 2, img))
    found = owned.list_owned(p.client)
    gateway = {r.kind for r in found if r.role is Role.GATEWAY}
    # (EC2 tags its interfaces from RunInstances' TagSpecifications too; moto does not)
    assert {"instance", "elastic_ip"} <= gateway <= {"instance", "elastic_ip", "volume", "network_interface"}, found
    assert all(r.robot == GATEWAY for r in found if r.role is Role.GATEWAY)
    assert {r.kind for r in found if r.role is Role.BOOTSTRAP} >= {"subnet", "route_table", "security_group"}
    assert len([r for r in found if r.kind == "subnet"]) == 2
    p.teardown()
    assert owned.leftovers(p.client) == []


def test_a_bakes_builder_behind_a_gateway_is_in_the_public_subnet_with_its_own_address(mocked, tmp_path):
    """It is reached and gets its packages whether the fleet's gateway runs or not."""
    p = make(tmp_path)
    spec = clone_spec(p.inv, "robot1", 1, image(p)).model_copy(update={
        "robot": "snapshot-builder", "role": "builder", "vpn_subnet": None})
    rec = p.run_instance(spec)
    inst = p.client.ec2.describe_instances(InstanceIds=[rec.provider_id])["Reservations"][0]["Instances"][0]
    assert rec.public_ip and inst["SubnetId"] == p.network.gateway_subnet_id


def test_a_route_left_to_a_dead_instance_of_the_robot_is_replaced_and_a_kept_one_untouched(mocked, tmp_path):
    p = make(tmp_path, **PER_CLONE)
    spec = clone_spec(p.inv, "robot2", 2, image(p))
    first = p.run_instance(spec)
    p.client.ec2.terminate_instances(InstanceIds=[first.provider_id])  # by hand: its route stays (a blackhole)

    def routes() -> dict:
        rt = p.client.ec2.describe_route_tables(RouteTableIds=[p.network.route_table_id])["RouteTables"][0]
        return {r["DestinationCidrBlock"]: r["InstanceId"] for r in rt["Routes"] if r.get("InstanceId")}

    assert routes() == {"10.80.2.0/24": first.provider_id}
    second = p.run_instance(spec)
    assert second.created and second.provider_id != first.provider_id
    assert routes() == {"10.80.2.0/24": second.provider_id}
    assert p.run_instance(spec).origin is Origin.REUSED and routes() == {"10.80.2.0/24": second.provider_id}
