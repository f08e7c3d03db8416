"""Quotas before growth (ccrp_cli/ops/quotas.py): `fleet up`, `clone create` and `fleet scale` hold the
clones they would create against the cloud's quotas and refuse in one line, creating nothing, when
one is short. Each cloud's quotas come from its fake: the GCE fake's regions.get, the OpenStack
fake's Nova limits and Neutron quota details, moto's account attributes (and a Service Quotas
answer injected where moto has none); every fake counts usage from what exists."""

from __future__ import annotations

import ipaddress
import json
import re
import sys

import pytest

from ccrp_cli.ops import quotas, reconcile
from ccrp_cli.ops.clones import CloneResult
from ccrp_cli.fleet import Fleet
from ccrp_cli.providers.base import Quota
from ccrp_cli.store import FleetStore
from tests.contract import specs

from .aws_fakes import REGION


def fleet_of(inv) -> Fleet:
    return Fleet(inv, FleetStore(inv.fleet))


def refused_line(fleet, provider, **kw) -> str:
    with pytest.raises(quotas.QuotaError) as err:
        reconcile.up(fleet, provider, lambda _m: None, **kw)
    line = err.value.one_line()
    assert "\n" not in line and err.value.code == 1
    return line


@pytest.fixture
def created(monkeypatch):
    """reconcile.up past the gate without booting anything: each clone it would create or reuse
    is recorded (ensure_clone stubbed); the gate and bootstrap run for real."""
    robots: list[str] = []

    def ensure(fleet, provider, writer, robot, progress, deployed=None):
        robots.append(robot)
        return CloneResult(robot, "created")

    monkeypatch.setattr(reconcile, "ensure_clone", ensure)
    monkeypatch.setattr(reconcile, "reshare", lambda *a, **k: [])
    return robots


# -- the decision, on typed records ---------------------------------------------------------------

def Q(name="STATIC_ADDRESSES", limit=8, used=5, per=1, **clones):
    return Quota(name=name, scope="region r", limit=limit, used=used, per_clone=per, per_robot=clones)


def test_refusal_names_each_short_quota_with_its_numbers_and_what_fits():
    creating = ["a", "b", "c", "d", "e"]
    found = [quotas.Use(q, q.need(creating)) for q in (Q(), Q("CPUS", 24, 14, 2, c=8), Q("INSTANCES", 100, 3))]
    err = quotas.refusal("gcp", found, creating)
    assert err.message == ("gcp quota STATIC_ADDRESSES in region r: 3 free, this needs 5; "
                           "gcp quota CPUS in region r: 10 free, this needs 16")
    # a, b fit (1+1 addresses, 2+2 CPUs); c's 8 CPUs would pass the 10 free.
    assert "or create at most 2 of the 5 new clones for now. Nothing was created" in err.hint
    assert quotas.refusal("gcp", found[2:], creating) is None
    assert quotas.fitting(found, []) == 0 and quotas.fitting(found[2:], creating) == 5


def test_a_robot_holding_its_address_needs_none_and_over_the_limit_is_zero_free():
    q = Q(limit=4, used=6, a=0)
    assert q.free == 0 and q.need(["a", "b"]) == 1
    assert quotas.Use(q, 1).short and not quotas.Use(q, 0).short


def test_a_backend_without_quotas_refuses_nothing():
    class Local:  # as the Docker provider: this host's CPUs are the limit, no quota is reported
        kind = "docker"

        def query(self):
            return {"a": object()}

        def quotas(self, robots=()):
            return []

    assert quotas.check_growth(None, Local(), [], print) == []
    assert quotas.check(Local(), ["b", "c"], print) == []


def test_unreadable_quotas_are_said_and_not_held_against(tmp_path):
    from google.api_core import exceptions

    from tests.contract.harness_gcp import GcpHarness

    h = GcpHarness(tmp_path)
    h.fake.clients.regions.get.side_effect = exceptions.Forbidden("Required 'compute.regions.get' permission")
    said: list[str] = []
    assert quotas.check(h.provider, ["robot1"], said.append) == []
    assert said and said[0].startswith("cannot read the gcp quotas (quotas of europe-west2:")


# -- GCP: the GCE fake's regional quotas (STATIC_ADDRESSES 8 by default, as a new project's) -------

@pytest.fixture
def gcp(tmp_path, ccrp_home):
    pytest.importorskip("google.cloud.compute_v1")
    from tests.contract.harness_gcp import FakeProject, GcpHarness

    def make(inv=None, **fake):
        h = GcpHarness(tmp_path / f"h{len(fake)}", FakeProject(**fake), inv=inv)
        h.provider.bootstrap()
        return h

    return make


def test_gcp_up_refuses_over_static_addresses_and_creates_nothing(gcp):
    h = gcp(address_quota=3)
    h.provider.run_instance(h.spec("robot1", 1))  # one clone up: one address reserved
    before, addresses = h.owned_ids(), set(h.fake.addresses)
    line = refused_line(fleet_of(h.inv), h.provider)
    assert line.startswith("gcp quota STATIC_ADDRESSES in region europe-west2: 2 free, this needs 4 (hint: ")
    assert "IAM & Admin > Quotas, STATIC_ADDRESSES in europe-west2" in line
    assert "or create at most 2 of the 4 new clones for now. Nothing was created" in line
    assert h.owned_ids() == before and set(h.fake.addresses) == addresses and len(h.fake.instances) == 1
    assert h.api_calls()["addresses.insert"] == 1 and h.api_calls()["instances.insert"] == 1  # robot1's only


def test_gcp_clone_create_fits_where_the_fleet_does_not(gcp, created):
    from ccrp_cli.ops import vpn

    h = gcp(address_quota=2)
    fleet = fleet_of(h.inv)
    vpn.init(fleet)
    assert [r.action for r in reconcile.up(fleet, h.provider, print, only=["robot2"])] == ["created"]
    assert created == ["robot2"]
    assert "STATIC_ADDRESSES in region europe-west2: 2 free, this needs 5" in refused_line(fleet, h.provider)


def test_gcp_scale_refuses_before_recording_new_robots(gcp):
    from tests.contract.harness_gcp import PROJECT, REGION as GCP_REGION, ZONES

    inv = specs.inventory({"kind": "gcp", "project": PROJECT, "region": GCP_REGION, "zones": ZONES[:2],
                           "operator_cidr": specs.OPERATOR_CIDR, "entry": "per-clone"}, template={"prefix": "extra"})
    h = gcp(inv=inv, cpu_quota=16, address_quota=20, in_use_address_quota=20)  # 8 clones of 2 vCPUs
    fleet, before = fleet_of(inv), h.owned_ids()
    with pytest.raises(quotas.QuotaError) as err:
        reconcile.scale(fleet, h.provider, 9, print)  # the five robots of the inventory and four more
    assert err.value.message == "gcp quota CPUS in region europe-west2: 16 free, this needs 18"
    assert "create at most 8 of the 9 new clones" in err.value.hint
    assert not any(r.origin == "template" for r in fleet.store.load_state().robots.values())
    assert h.owned_ids() == before and h.fake.instances == {} and h.fake.addresses == {}


def test_gcp_scale_that_fits_records_and_creates_the_new_robots(gcp, created):
    from ccrp_cli.ops import vpn
    from tests.contract.harness_gcp import PROJECT, REGION as GCP_REGION, ZONES

    inv = specs.inventory({"kind": "gcp", "project": PROJECT, "region": GCP_REGION, "zones": ZONES[:2],
                           "operator_cidr": specs.OPERATOR_CIDR, "entry": "per-clone"}, template={"prefix": "extra"})
    h = gcp(inv=inv, cpu_quota=16, address_quota=20, in_use_address_quota=20)
    fleet = fleet_of(inv)
    vpn.init(fleet)
    kept, new, removed = reconcile.scaled(fleet, fleet.store.load_state(), 8)
    assert (len(kept), new, removed) == (5, ["extra1", "extra2", "extra3"], [])
    assert len(reconcile.scale(fleet, h.provider, 8, print)) == 8 and sorted(created)[:3] == new
    assert sorted(n for n, r in fleet.store.load_state().robots.items() if r.origin == "template") == new


def test_gcp_fake_reports_usage_from_what_exists(gcp):
    h = gcp()
    h.provider.run_instance(h.spec("robot1", 1))
    h.provider.run_instance(h.spec("robot2", 2))
    h.provider.stop_instance("robot2")
    got = {q.name: (q.limit, q.used) for q in h.provider.quotas(["robot3"])}
    # A stopped instance's vCPUs are free again; its reserved address stays reserved and in use.
    assert got == {"CPUS": (24, 2), "IN_USE_ADDRESSES": (8, 2), "STATIC_ADDRESSES": (8, 2)}


def test_gcp_machine_type_of_a_robot_and_another_familys_cpus(tmp_path):
    from ccrp_cli.providers.gcp.provider import cpu_metric
    from tests.contract.harness_gcp import GcpHarness, inventory

    assert [cpu_metric(m) for m in ("e2-medium", "n1-standard-4", "custom-2-4096", "n2-standard-8", "c3-highcpu-4")] \
        == ["CPUS", "CPUS", "CPUS", "N2_CPUS", "C3_CPUS"]
    inv = inventory()
    inv.robots[2].instance_type = "e2-standard-4"
    h = GcpHarness(tmp_path, inv=inv)
    cpus = next(q for q in h.provider.quotas(["robot1", "robot3"]) if q.name == "CPUS")
    assert (cpus.per_clone, cpus.per_robot, cpus.need(["robot1", "robot3"])) == (2, {"robot3": 4}, 6)
    assert h.api_calls()["machine_types.get"] == 2  # once per machine type


# -- OpenStack: Nova's compute limits and Neutron's floating-IP quota -------------------------------

@pytest.fixture
def openstack(tmp_path, ccrp_home):
    pytest.importorskip("openstack")
    from tests.contract.harness_openstack import make_harness

    with make_harness(tmp_path) as h:
        yield h


def test_openstack_up_refuses_over_floating_ips_and_cores_and_creates_nothing(openstack):
    h = openstack
    h.fake.max_fips, h.fake.max_cores = 3, 6
    h.provider.run_instance(h.spec("robot1", 1))
    before, servers, fips = h.owned_ids(), len(h.fake.servers), len(h.fake.fips)
    line = refused_line(fleet_of(h.provider.inv), h.provider)
    assert line.startswith("openstack quota cores in project of cloud 'ccrp-fake': 4 free, this needs 8; "
                           "openstack quota floating-ips in project of cloud 'ccrp-fake': 2 free, this needs 4 (hint: ")
    assert "`openstack quota show`" in line and "create at most 2 of the 4 new clones" in line
    assert h.owned_ids() == before and (len(h.fake.servers), len(h.fake.fips)) == (servers, fips)


def test_openstack_fake_enforces_what_it_reports(openstack):
    from ccrp_cli.errors import CcrpError

    h = openstack
    h.fake.max_fips = 1
    h.provider.run_instance(h.spec("robot1", 1))
    assert {q.name: (q.limit, q.used) for q in h.provider.quotas()}["floating-ips"] == (1, 1)
    with pytest.raises(CcrpError, match=r"floatingip"):
        h.provider.run_instance(h.spec("robot2", 2))
    assert h.instances_for("robot2") == 0 and len(h.fake.fips) == 1  # rolled back


def test_openstack_without_quota_details_checks_the_compute_limits(openstack):
    h = openstack
    h.fake.fail_next[("GET", "network:/v2.0/quotas/{id}/details")] = (404, "The resource could not be found.")
    assert [q.name for q in h.provider.quotas(["robot1"])] == ["instances", "cores", "ram (MB)"]


def test_openstack_happy_path_passes_the_gate(openstack, created):
    from ccrp_cli.ops import vpn

    fleet = fleet_of(openstack.provider.inv)
    vpn.init(fleet)
    assert len(reconcile.up(fleet, openstack.provider, print)) == 5 and len(created) == 5


# -- AWS on moto: account attributes (vpc-max-elastic-ips 5, max-instances 20), Service Quotas ------

INVENTORY = """\
fleet: {fleet}
provider: {{kind: aws, region: {region}, zones: [us-east-1a], operator_cidr: 198.51.100.0/24, entry: {entry}}}
robots:
{robots}
template: {{prefix: extra}}
"""


def write_inventory(path, robots: int, fleet: str = "quotas", entry: str = "per-clone"):
    """A fleet whose clones each hold an Elastic IP (entry: per-clone), or behind AWS's default entry gateway."""
    path.write_text(INVENTORY.format(fleet=fleet, region=REGION, entry=entry,
                                     robots="\n".join(f"  - name: robot{i}" for i in range(1, robots + 1))))
    return path


def ec2_counts(ec2) -> tuple[int, int]:
    live = [i for r in ec2.describe_instances()["Reservations"] for i in r["Instances"]
            if i["State"]["Name"] not in ("shutting-down", "terminated")]
    return len(live), len(ec2.describe_addresses()["Addresses"])


def test_aws_fleet_up_plan_and_scale_refuse_over_elastic_ips(moto_url, ccrp_home, ccrp, tmp_path):
    import boto3

    ec2 = boto3.client("ec2", region_name=REGION)
    ec2.allocate_address(Domain="vpc")  # someone else's, in the same account and region
    path = write_inventory(tmp_path / "aws.yaml", 5)

    plan = ccrp("fleet", "plan", "-i", str(path))
    assert plan.returncode == 0, plan.stderr
    assert "quotas: 5 clones to create" in plan.stdout
    row = next(line.split() for line in plan.stdout.splitlines() if line.startswith("EC2-VPC Elastic IPs"))
    assert row[-7:] == ["us-east-1", "5", "1", "1", "5", "-1", "(short)"]  # limit, used, per clone, needs, after
    assert "`fleet up` would refuse, creating nothing: aws quota EC2-VPC Elastic IPs in region us-east-1: " \
           "4 free, this needs 5" in plan.stderr
    assert json.loads(ccrp("fleet", "plan", "-i", str(path), "--json").stdout)[0] == {
        "robot": "robot1", "action": "create", "provider_id": None, "software": None, "endpoint": None}

    up = ccrp("fleet", "up", "-i", str(path))
    assert up.returncode == 1
    assert up.stderr.strip().splitlines()[-1] == (
        "ccrp: error: aws quota EC2-VPC Elastic IPs in region us-east-1: 4 free, this needs 5 (hint: raise EC2-VPC "
        "Elastic IPs (L-0263D0A3) in the Service Quotas console; or create at most 4 of the 5 new clones for now. "
        "Nothing was created)")
    assert ec2_counts(ec2) == (0, 1)
    assert not ec2.describe_vpcs(Filters=[{"Name": "tag:ccrp-fleet", "Values": ["quotas"]}])["Vpcs"]  # no bootstrap

    small = write_inventory(tmp_path / "small.yaml", 2, fleet="quotas2")
    scale = ccrp("fleet", "scale", "6", "-i", str(small))
    assert scale.returncode == 1
    assert "aws quota EC2-VPC Elastic IPs in region us-east-1: 4 free, this needs 6" in scale.stderr
    assert ec2_counts(ec2) == (0, 1)
    state = Fleet.open(small).store.load_state()
    assert not any(r.origin == "template" for r in state.robots.values())  # no new robot recorded

    one = ccrp("clone", "create", "--robot", "robot1", "-i", str(path))
    assert "quota" not in one.stderr  # one clone fits: it goes on (and fails later: no snapshot)


class _Answer:
    """Answers the service-quotas client's GetServiceQuota with `value` (moto has no EC2 quotas)."""

    def __init__(self, client, value: float) -> None:
        from botocore.awsrequest import AWSResponse

        reply = (AWSResponse("https://servicequotas.amazonaws.com/", 200, {}, None),
                 {"Quota": {"ServiceCode": "ec2", "QuotaCode": "L-1216C47A", "Value": value},
                  "ResponseMetadata": {"HTTPStatusCode": 200}})
        client.meta.events.register("before-call.service-quotas.GetServiceQuota", lambda **_: reply)


def test_aws_vcpu_quota_counts_running_standard_instances_and_each_robots_type(aws_env, tmp_path, ccrp_home):
    from moto import mock_aws

    from ccrp_cli.providers.aws.provider import AwsProvider, is_standard

    assert [is_standard(t) for t in ("t3.medium", "m5.xlarge", "g5.xlarge", "inf2.xlarge", "mac1.metal")] == \
        [True, True, False, False, False]
    with mock_aws():
        inv = specs.inventory({"kind": "aws", "region": REGION, "zones": ["us-east-1a"],
                               "operator_cidr": specs.OPERATOR_CIDR})
        inv.robots[1].instance_type = "m5.xlarge"
        p = AwsProvider(inv, tmp_path / "store")
        p._service_quotas = p.client.session.client("service-quotas")
        _Answer(p._service_quotas, 12)
        image = p.client.ec2.register_image(Name="base", RootDeviceName="/dev/sda1", Architecture="x86_64")["ImageId"]
        p.client.ec2.run_instances(ImageId=image, MinCount=1, MaxCount=1, InstanceType="t3.medium")  # 2 vCPUs
        p.client.ec2.run_instances(ImageId=image, MinCount=1, MaxCount=1, InstanceType="g5.xlarge")  # not standard
        got = {q.name: q for q in p.quotas(["robot1", "robot2", "robot3"])}
        vcpus = got["Running On-Demand Standard instances (vCPUs)"]
        assert (vcpus.limit, vcpus.used, vcpus.per_clone, vcpus.per_robot) == (12, 2, 2, {"robot2": 4})
        assert vcpus.once == 2  # the entry gateway (AWS's default), a t3.micro, while the fleet has none
        assert "max-instances (running instances)" not in got
        fleet = fleet_of(inv)
        line = refused_line(fleet, p)
        assert "aws quota Running On-Demand Standard instances (vCPUs) in region us-east-1: 10 free, " \
               "this needs 14" in line and "L-1216C47A" in line
        assert "create at most 3 of the 5 new clones" in line  # the gateway's 2 + 2 + 4 + 2 of the 10
        assert len(p.client.ec2.describe_instances()["Reservations"]) == 2


def test_aws_without_service_quotas_counts_running_instances(aws_env, tmp_path):
    from moto import mock_aws

    from ccrp_cli.providers.aws.provider import AwsProvider

    with mock_aws():
        p = AwsProvider(specs.inventory({"kind": "aws", "region": REGION, "zones": ["us-east-1a"],
                                         "operator_cidr": specs.OPERATOR_CIDR}), tmp_path / "store")
        got = {q.name: (q.limit, q.used, q.per_clone, q.once) for q in p.quotas(["robot1"])}
        # behind the entry gateway (AWS's default): its instance and the fleet's one address, once;
        # moto's Service Quotas knows the VPC's defaults (50 routes per table), not EC2's.
        assert got == {"EC2-VPC Elastic IPs": (5, 0, 0, 1), "max-instances (running instances)": (20, 0, 1, 1),
                       "Routes per route table": (50, 1, 1, 0)}


def test_aws_routes_per_route_table_hold_a_fleet_of_49_clones(aws_env, tmp_path):
    """Each clone has a route in the clones' route table (its robot's VPN subnet): AWS's default of 50
    routes per table (Service Quotas L-93826ACB) holds the default route and 49 clones, so a fleet of 100
    needs that quota raised even behind the entry gateway (one address)."""
    from moto import mock_aws

    from ccrp_cli.providers.aws.provider import AwsProvider

    with mock_aws():
        p = AwsProvider(specs.inventory({"kind": "aws", "region": REGION, "zones": ["us-east-1a"],
                                         "operator_cidr": specs.OPERATOR_CIDR}), tmp_path / "store")
        robots = [f"robot{i}" for i in range(1, 101)]
        [routes] = [q for q in p.quotas(robots) if q.name == "Routes per route table"]
        assert (routes.limit, routes.used, routes.need(robots[:49]), routes.need(robots)) == (50, 1, 49, 100)
        assert "L-93826ACB" in routes.hint
        p.bootstrap()
        p.client.ec2.create_route(RouteTableId=p.network.route_table_id, DestinationCidrBlock="10.80.7.0/24",
                                  GatewayId=p.client.ec2.describe_internet_gateways()["InternetGateways"][0]["InternetGatewayId"])
        [routes] = [q for q in p.quotas(robots) if q.name == "Routes per route table"]
        assert (routes.used, routes.free) == (2, 48)  # the default route and the one above; not the local one


# -- the fakes hold their cloud's default address quotas and refuse the one over as the cloud does ----

def quota_rows(plan: str) -> dict[str, list[str]]:
    """The rows of `fleet plan`'s quota table: quota -> its other columns."""
    lines = plan.splitlines()
    table = lines[next(n for n, line in enumerate(lines) if line.startswith("QUOTA ")) + 1:]
    return {cells[0]: cells[1:] for line in table if len(cells := re.split(r"\s{2,}", line.strip())) > 1}


class _NoDocker:
    """What an AwsBoot asks of its CloudBoot before any instance boots: here no Docker at all (its
    "internet" a range nothing uses, Elastic IPs only allocated, never attached)."""

    def base_image(self) -> str:
        from tests.fakes.cloudboot import DEBIAN_12

        return DEBIAN_12

    def claim_network(self, name: str, within: str, prefix: int = 24) -> tuple[str, str]:
        return name, "172.28.250.0/24"

    def cleanup(self) -> None:
        pass


@pytest.fixture
def aws_boot(aws_env):
    """The booting EC2 fake (tests/fakes/aws_boot.py), served for requests that boot nothing."""
    pytest.importorskip("moto.server")
    pytest.importorskip("docker")
    from tests.fakes.aws_boot import AwsBoot

    with AwsBoot(boot=_NoDocker(), progress=lambda _m: None) as fake:
        yield fake


def test_aws_fake_refuses_the_elastic_ip_over_the_regions_default_as_ec2_does(aws_boot):
    from botocore.exceptions import ClientError

    from ccrp_cli.providers.aws.errors import classify
    from ccrp_cli.retry import ErrorClass
    from tests.fakes.aws_boot import EIP_LIMIT

    ec2 = aws_boot.client()
    attrs = {a["AttributeName"]: a["AttributeValues"] for a in ec2.describe_account_attributes()["AccountAttributes"]}
    assert EIP_LIMIT == 5 and attrs["vpc-max-elastic-ips"] == [{"AttributeValue": "5"}]  # what it enforces is what it says
    held = [ec2.allocate_address(Domain="vpc")["AllocationId"] for _ in range(EIP_LIMIT)]
    with pytest.raises(ClientError) as err:
        ec2.allocate_address(Domain="vpc")
    assert err.value.response["ResponseMetadata"]["HTTPStatusCode"] == 400
    assert err.value.response["Error"] == {"Code": "AddressLimitExceeded",
                                           "Message": "The maximum number of addresses has been reached."}
    assert classify(err.value) is ErrorClass.REGION
    assert len(ec2.describe_addresses()["Addresses"]) == EIP_LIMIT
    ec2.release_address(AllocationId=held[0])  # one released: one more fits again
    ec2.allocate_address(Domain="vpc")


def test_aws_fleet_plan_of_ten_robots_does_not_fit_the_default_elastic_ips(aws_boot, ccrp, tmp_path, monkeypatch):
    for key, value in aws_boot.env().items():
        monkeypatch.setenv(key, value)
    plan = ccrp("fleet", "plan", "-i", str(write_inventory(tmp_path / "aws.yaml", 10)))
    assert plan.returncode == 0, plan.stderr
    assert quota_rows(plan.stdout) == {  # where, limit, used, per clone, this needs, free after
        "EC2-VPC Elastic IPs": ["region us-east-1", "5", "0", "1", "10", "-5 (short)"],
        "max-instances (running instances)": ["region us-east-1", "20", "0", "1", "10", "10"],
        # moto's Service Quotas answers AWS's default for the VPC's (50): the default route and a route a clone
        "Routes per route table": ["the clones' route table of fleet 'quotas'", "50", "1", "1", "10", "39"]}
    assert "`fleet up` would refuse, creating nothing: aws quota EC2-VPC Elastic IPs in region us-east-1: " \
           "5 free, this needs 10 (hint: " in plan.stderr  # the addresses alone are short


@pytest.mark.parametrize("robots", [10, 50, 100])
def test_aws_fleet_plan_behind_the_default_gateway_needs_one_elastic_ip_whatever_its_size(
        aws_boot, ccrp, tmp_path, monkeypatch, robots):
    """AWS's default entry (gateway): the fleet's one Elastic IP on its gateway, none per clone, on
    the default-quota account the fake holds (5 Elastic IPs, 20 instances); the instances stay
    exact, the gateway counted."""
    for key, value in aws_boot.env().items():
        monkeypatch.setenv(key, value)
    plan = ccrp("fleet", "plan", "-i", str(write_inventory(tmp_path / "aws.yaml", robots, entry="gateway")))
    assert plan.returncode == 0, plan.stderr
    rows = quota_rows(plan.stdout)  # where, limit, used, per clone, this needs, free after
    assert rows["EC2-VPC Elastic IPs"] == ["region us-east-1", "5", "0", "0", "1", "4"]
    after = 20 - robots - 1
    assert rows["max-instances (running instances)"] == \
        ["region us-east-1", "20", "0", "1", str(robots + 1), str(after) if after >= 0 else f"{after} (short)"]
    # Each clone's route (its robot's VPN subnet) in the clones' table: 50 hold the default route and 49.
    routes = 49 - robots
    assert rows["Routes per route table"] == ["the clones' route table of fleet 'quotas'", "50", "1", "1", str(robots),
                                              str(routes) if routes >= 0 else f"{routes} (short)"]
    assert "Elastic IPs" not in plan.stderr
    refused = "`fleet up` would refuse, creating nothing: aws quota max-instances (running instances) in region " \
              f"us-east-1: 20 free, this needs {robots + 1}"
    assert (refused in plan.stderr) is (robots + 1 > 20), plan.stderr


def test_gce_fake_refuses_the_address_over_each_default_quota_as_gce_does(gcp):
    from google.api_core import exceptions
    from google.cloud import compute_v1 as c

    from ccrp_cli.providers.gcp.errors import classify
    from ccrp_cli.retry import ErrorClass
    from tests.contract.harness_gcp import PROJECT, PUBLIC_IMAGE, REGION as GCP_REGION, ZONES

    h = gcp()  # a new project's quotas: 8 static addresses, 8 external IPs in use
    addresses = h.fake.clients.addresses
    for n in range(8):
        addresses.insert(project=PROJECT, region=GCP_REGION, address_resource=c.Address(name=f"a{n}")).result()
    with pytest.raises(exceptions.Forbidden) as err:
        addresses.insert(project=PROJECT, region=GCP_REGION, address_resource=c.Address(name="a8")).result()
    assert err.value.code == 403 and classify(err.value) is ErrorClass.REGION
    assert str(err.value.message) == "Quota 'STATIC_ADDRESSES' exceeded.  Limit: 8.0 in region europe-west2."
    assert len(h.fake.addresses) == 8

    subnet = next(iter(h.fake.subnetworks.values()))
    hosts = list(ipaddress.ip_network(subnet.ip_cidr_range).hosts())[10:]

    def insert(n: int):
        return h.fake.clients.instances.insert(project=PROJECT, zone=ZONES[0], instance_resource=c.Instance(
            name=f"vm{n}", machine_type=f"zones/{ZONES[0]}/machineTypes/e2-micro",
            disks=[c.AttachedDisk(boot=True, initialize_params=c.AttachedDiskInitializeParams(source_image=PUBLIC_IMAGE))],
            network_interfaces=[c.NetworkInterface(subnetwork=subnet.self_link, network_i_p=str(hosts[n]),
                                                   access_configs=[c.AccessConfig(name="External NAT")])])).result()

    for n in range(8):
        insert(n)
    with pytest.raises(exceptions.Forbidden) as err:
        insert(8)
    assert err.value.code == 403 and classify(err.value) is ErrorClass.REGION
    assert str(err.value.message) == "Quota 'IN_USE_ADDRESSES' exceeded.  Limit: 8.0 in region europe-west2."
    assert len(h.fake.instances) == 8
    got = {q.name: (q.limit, q.used) for q in h.provider.quotas(["robot1"])}
    assert got["STATIC_ADDRESSES"] == (8, 8) and got["IN_USE_ADDRESSES"] == (8, 8)


def gcp_fleet_plan(gcp, tmp_path, monkeypatch, capsys, robots: int, entry: str = ""):
    """`ccrp fleet plan` of `robots` robots on a new project's quotas (the GCE fake's defaults):
    (exit code, stdout, stderr)."""
    from ccrp_cli import providers
    from ccrp_cli.cli.main import run
    from ccrp_cli.providers.gcp.provider import GcpProvider
    from tests.contract.harness_gcp import PROJECT, REGION as GCP_REGION, ZONES

    h = gcp()
    path = tmp_path / "gcp.yaml"
    path.write_text(f"fleet: quotas\nprovider: {{kind: gcp, project: {PROJECT}, region: {GCP_REGION}, "
                    f"zones: [{ZONES[0]}], operator_cidr: 198.51.100.0/24{', entry: ' + entry if entry else ''}}}\n"
                    "common: {cidr: 10.90.0.0/16}\nrobots:\n" + "".join(f"  - name: robot{i}\n" for i in range(1, robots + 1)))
    monkeypatch.setattr(providers, "get_provider",
                        lambda inv, workdir=None: GcpProvider(inv, tmp_path / "store", clients=h.fake.clients))
    monkeypatch.setattr(sys, "argv", ["ccrp", "fleet", "plan", "-i", str(path)])
    with pytest.raises(SystemExit) as done:
        run()
    out = capsys.readouterr()
    return done.value.code, out.out, out.err


def test_gcp_fleet_plan_of_ten_robots_per_clone_does_not_fit_the_default_addresses(gcp, tmp_path, monkeypatch, capsys):
    code, out, err = gcp_fleet_plan(gcp, tmp_path, monkeypatch, capsys, 10, entry="per-clone")
    assert code == 0, err
    assert quota_rows(out) == {  # where, limit, used, per clone, this needs, free after
        "CPUS": ["region europe-west2", "24", "0", "2", "20", "4"],
        "IN_USE_ADDRESSES": ["region europe-west2", "8", "0", "1", "10", "-2 (short)"],
        "STATIC_ADDRESSES": ["region europe-west2", "8", "0", "1", "10", "-2 (short)"]}
    assert ("`fleet up` would refuse, creating nothing: gcp quota IN_USE_ADDRESSES in region europe-west2: 8 free, "
            "this needs 10; gcp quota STATIC_ADDRESSES in region europe-west2: 8 free, this needs 10") in err


@pytest.mark.parametrize("robots", [10, 50, 100])
def test_gcp_fleet_plan_behind_the_default_gateway_needs_one_address_whatever_the_size(
        gcp, tmp_path, monkeypatch, capsys, robots):
    """provider.entry: gateway, GCP's default: the fleet's one reserved address and one IP in use
    (the gateway's), however many clones; instances and vCPUs stay exact, the gateway counted."""
    code, out, err = gcp_fleet_plan(gcp, tmp_path, monkeypatch, capsys, robots)
    assert code == 0, err
    rows = quota_rows(out)
    assert rows["IN_USE_ADDRESSES"] == ["region europe-west2", "8", "0", "0", "1", "7"]
    assert rows["STATIC_ADDRESSES"] == ["region europe-west2", "8", "0", "0", "1", "7"]
    cpus = 2 * (robots + 1)  # e2-medium: 2 vCPUs each, the gateway's too
    assert rows["CPUS"] == ["region europe-west2", "24", "0", "2", str(cpus),
                            str(24 - cpus) + (" (short)" if cpus > 24 else "")]
    assert "ADDRESSES" not in "".join(line for line in err.splitlines() if "would refuse" in line)
    assert ("`fleet up` would refuse" in err) is (cpus > 24)  # the CPUs alone, past 11 robots


def test_openstack_fake_refuses_the_floating_ip_over_neutrons_default_as_neutron_does(openstack):
    from openstack.exceptions import ConflictException

    from ccrp_cli.providers.openstack.errors import classify
    from ccrp_cli.retry import ErrorClass

    h = openstack
    assert h.fake.max_fips == 50  # Neutron's default quota_floatingip
    assert {q.name: (q.limit, q.used) for q in h.provider.quotas()}["floating-ips"] == (50, 0)
    net = h.provider.client.network
    public = net.find_network("public")
    for _ in range(50):
        net.create_ip(floating_network_id=public.id)
    with pytest.raises(ConflictException) as err:
        net.create_ip(floating_network_id=public.id)
    assert err.value.status_code == 409 and "Quota exceeded for resources: ['floatingip']." in str(err.value)
    assert classify(err.value) is ErrorClass.REGION and len(h.fake.fips) == 50
