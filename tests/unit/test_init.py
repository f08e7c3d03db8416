"""`ccrp init` and the default inventory: a fleet starts from nothing, commands work as typed."""

from __future__ import annotations

import ipaddress
import json
import os
from pathlib import Path

import pytest

from ccrp_cli.loader import load_inventory
from tests.inprocess_cli import run_ccrp_inprocess


@pytest.fixture
def here(tmp_path, monkeypatch) -> Path:
    work = tmp_path / "lab2"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.delenv("CCRP_INVENTORY", raising=False)
    return work


@pytest.mark.parametrize("provider", ["docker", "libvirt", "openstack", "gcp", "aws"])
def test_init_writes_an_inventory_that_validates(here, provider):
    code, out, err = run_ccrp_inprocess("init", "--provider", provider, "--robots", "nao1,tb1", "--json", home=here / "home")
    assert code == 0, err
    inv = load_inventory(here / "ccrp.yaml")
    assert (inv.fleet, inv.provider.kind, [r.name for r in inv.robots]) == ("lab2", provider, ["nao1", "tb1"])
    assert json.loads(out)["path"] == "ccrp.yaml"
    assert (here / "ccrp.yaml").read_text().startswith("# ccrp fleet lab2")


GOLDEN = Path(__file__).resolve().parents[1] / "golden" / "init"


@pytest.mark.parametrize("distro", ["jazzy", "noetic"])
@pytest.mark.parametrize("provider", ["docker", "openstack", "gcp", "aws"])
def test_init_writes_each_backends_inventory_as_before(tmp_path, monkeypatch, provider, distro):
    """Byte for byte what `ccrp init` wrote before each backend's section moved into its own package
    (tests/golden/init, pools from a host with nothing on it)."""
    from ccrp_cli.ops import init

    monkeypatch.setattr(init, "used_networks", lambda: [])
    got = init.write(tmp_path / "ccrp.yaml", provider, ["nao1", "tb1"], "lab", distro)
    assert (tmp_path / "ccrp.yaml").read_text() == (GOLDEN / f"{provider}-{distro}.yaml").read_text()
    assert got == {"path": str(tmp_path / "ccrp.yaml"), "fleet": "lab", "provider": provider, "distro": distro,
                   "robots": ["nao1", "tb1"], "public": "172.30.0.0/24" if provider == "docker" else None,
                   "common": "10.90.0.0/24", "vpn_pool": "10.80.0.0/16"}


def test_init_never_overwrites_and_refuses_bad_input(here):
    (here / "ccrp.yaml").write_text("mine\n")
    for argv in (("init",), ("init", "-o", "a.yaml", "--provider", "azure"), ("init", "-o", "b.yaml", "--robots", "nao1,NAO2"),
                 ("init", "-o", "c.yaml", "--robots", "nao1,nao1"), ("init", "-o", "d.yaml", "--fleet", "My Fleet"),
                 ("init", "-o", "e.yaml", "--distro", "humble")):
        code, _, err = run_ccrp_inprocess(*argv, home=here / "home")
        assert code == 2 and err.startswith("ccrp: error: ") and err.count("\n") == 1, (argv, err)
    assert (here / "ccrp.yaml").read_text() == "mine\n"
    assert sorted(p.name for p in here.iterdir()) == ["ccrp.yaml"]


def test_init_makes_a_ros2_fleet_and_says_how_to_pick_noetic(here):
    """A new fleet is ROS 2 Jazzy (the current LTS); the output names the flag for a ROS 1 fleet,
    and that flag gives one."""
    code, out, err = run_ccrp_inprocess("init", "--json", home=here / "home")
    assert code == 0, err
    inv = load_inventory(here / "ccrp.yaml")
    assert (inv.ros.distro, inv.ros.ros2, json.loads(out)["distro"]) == ("jazzy", True, "jazzy")
    assert inv.provider.kind == json.loads(out)["provider"] == "docker"  # no --provider: clones on this host
    assert "ccrp init --distro noetic" in err, err
    code, _, err = run_ccrp_inprocess("init", "-o", "ros1.yaml", "--distro", "noetic", home=here / "home")
    assert code == 0, err
    inv = load_inventory(here / "ros1.yaml")
    assert (inv.ros.distro, inv.ros.ros2) == ("noetic", False)
    assert "--distro noetic" not in err


def test_init_libvirt_gets_a_nat_network_free_on_this_host(here, monkeypatch):
    """`ccrp init --provider libvirt`: the fleet's NAT network (provider.public_cidr) is a /24 no
    route, Docker network, other fleet or libvirt network of this host uses, running or not (a
    stopped libvirt network has no route yet); its pools do not overlap it."""
    from ccrp_cli.ops import init
    from ccrp_cli.providers.libvirt import host_networks

    nets = here / "networks"
    nets.mkdir()
    # libvirt's own forms: a netmask (its `default`), a prefix, an IPv6 range (not ours to avoid)
    (nets / "default.xml").write_text("<network><name>default</name><ip address='172.30.0.1' netmask='255.255.255.0'/></network>")
    (nets / "lab.xml").write_text("<network><name>lab</name><ip address='172.30.1.1' prefix='24'/>"
                                  "<ip family='ipv6' address='fd00::1' prefix='64'/></network>")
    (nets / "broken.xml").write_text("<network><ip address=")
    monkeypatch.setattr(host_networks, "NETWORKS", str(nets))
    assert {k: v for k, v in init.host_ranges().items() if v.startswith("libvirt")} == {
        "172.30.0.0/24": "libvirt network default", "172.30.1.0/24": "libvirt network lab"}
    code, out, err = run_ccrp_inprocess("init", "--provider", "libvirt", "--robots", "nao1", "--distro", "noetic",
                                        "--json", home=here / "home")
    assert code == 0, err
    got = json.loads(out)
    inv = load_inventory(here / "ccrp.yaml")
    p = inv.provider
    assert (p.kind, p.uri, p.accel, p.memory_mb, p.vcpus) == ("libvirt", "qemu:///system", "auto", 2048, 2)
    assert str(p.public_cidr) == got["public"] and p.public_cidr.prefixlen == 24
    # the search range's first two /24s are the libvirt networks' (others may be this host's Docker networks)
    assert p.public_cidr.subnet_of(ipaddress.IPv4Network("172.30.0.0/15")) and got["public"] not in ("172.30.0.0/24", "172.30.1.0/24")
    assert not any(p.public_cidr.overlaps(ipaddress.IPv4Network(r)) for r in init.host_ranges())
    assert not p.public_cidr.overlaps(inv.common.cidr) and not p.public_cidr.overlaps(inv.vpn.pool)
    assert "docs/libvirt.md" in (here / "ccrp.yaml").read_text()


def test_init_pools_avoid_the_fleets_in_ccrp_home(here):
    """Another fleet's clones use 10.90.0.0/24 and 10.80.0.0/16: the new fleet gets the next free ones."""
    other = here / "home" / "lab" / "state.json"
    other.parent.mkdir(parents=True)
    other.write_text(json.dumps({"fleet": "lab", "robots": {"nao1": {"index": 1, "addresses": {
        "common": "10.90.0.1", "vpn": "10.80.1.1", "public": "172.30.0.2"}}}}))
    code, out, err = run_ccrp_inprocess("init", "--json", home=here / "home")
    assert code == 0, err
    got = json.loads(out)
    assert got["common"] != "10.90.0.0/24" and got["vpn_pool"] != "10.80.0.0/16", got
    inv = load_inventory(here / "ccrp.yaml")
    assert str(inv.common.cidr) == got["common"] and str(inv.vpn.pool) == got["vpn_pool"]


def test_commands_find_ccrp_yaml_here_or_above(here):
    code, _, _ = run_ccrp_inprocess("init", "--robots", "nao1", home=here / "home")
    assert code == 0
    sub = here / "a" / "b"
    sub.mkdir(parents=True)
    os.chdir(sub)
    code, out, err = run_ccrp_inprocess("fleet", "validate", "--json", home=here / "home")
    assert code == 0, err
    assert f"ccrp: using inventory {here / 'ccrp.yaml'}" in err
    assert json.loads(out)["fleet"] == "lab2"


def test_no_inventory_anywhere_is_one_line(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("CCRP_INVENTORY", raising=False)
    code, _, err = run_ccrp_inprocess("clone", "create", "--robot", "nao1", home=tmp_path / "home")
    assert code == 2 and "no inventory" in err and "ccrp init" in err and err.count("\n") == 1, err
    assert not (tmp_path / "home").exists()


def test_commands_as_typed_in_a_new_fleet_make_its_pki(here):
    """`ccrp vpn issue-cert --robot nao1` in a directory with only a ccrp.yaml: the fleet's CA is
    made first, saying so; the certificates verify against it."""
    import subprocess

    assert run_ccrp_inprocess("init", "--robots", "nao1", home=here / "home")[0] == 0
    code, out, err = run_ccrp_inprocess("vpn", "issue-cert", "--robot", "nao1", "--json", home=here / "home")
    assert code == 0, err
    assert "had no PKI yet: created its CA" in err
    pki = here / "home" / "lab2" / "pki"
    for rec in json.loads(out):
        proc = subprocess.run(["openssl", "verify", "-CAfile", str(pki / "ca.crt"), rec["path"]], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stdout + proc.stderr
    code, _, err = run_ccrp_inprocess("vpn", "issue-cert", "--robot", "nao1", home=here / "home")
    assert code == 0 and "had no PKI yet" not in err
    code, _, err = run_ccrp_inprocess("vpn", "issue-cert", "--robot", "ghost", home=here / "home")
    assert code == 2 and err.splitlines() == ["ccrp: using inventory ccrp.yaml",
                                              "ccrp: error: robot 'ghost' is not in fleet 'lab2' (robots: nao1)"], err


@pytest.fixture
def fake_cloud(tmp_path, monkeypatch):
    """`ccrp init --cloud ccrp-fake` against the in-memory OpenStack (tests/fakes/openstack_cloud.py),
    reached through openstacksdk's real connection; this host's route is the test's to say."""
    pytest.importorskip("openstack")
    import openstack

    from ccrp_cli.providers.openstack import client, discover
    from tests.contract.harness_openstack import _isolated_env
    from tests.fakes.openstack_cloud import FakeOpenStack

    fake = FakeOpenStack()
    config = fake.clouds_yaml(tmp_path, "ccrp-fake")

    def connect(cloud):
        conn = openstack.connect(cloud=cloud)
        fake.attach(conn)
        return conn

    monkeypatch.setattr(client, "_connect", connect)
    routes = {}
    monkeypatch.setattr(discover, "_source_address", lambda target: routes.get(target))
    with _isolated_env(OS_CLIENT_CONFIG_FILE=str(config), OS_CLIENT_SECURE_FILE=str(tmp_path / "none.yaml")):
        yield fake, routes


def test_init_cloud_asks_openstack_for_flavor_network_and_this_hosts_address(here, fake_cloud):
    """The values a first inventory needs, from the cloud: the smallest flavor a clone fits in, the
    external network, and this host's address when the cloud sees it as it is (on the external
    network's subnet here, as with scripts/openstack.sh's cloud); behind NAT the placeholder stays."""
    import ipaddress as ip

    fake, routes = fake_cloud
    fake.add_flavor("tiny", vcpus=1, ram=512, disk=1)
    fake.add_flavor("c1.clone", vcpus=1, ram=2048, disk=20)
    subnet = next(s for s in fake.subnets.values() if s["name"] == "public-v4")
    inside = str(next(ip.IPv4Network(subnet["cidr"]).hosts()))
    routes["identity.example.com"] = ip.IPv4Address(inside)
    code, out, err = run_ccrp_inprocess("init", "--provider", "openstack", "--cloud", "ccrp-fake", "--json", home=here / "home")
    assert code == 0, err
    inv = load_inventory(here / "ccrp.yaml")
    assert (inv.provider.cloud, inv.provider.flavor, inv.provider.external_network) == ("ccrp-fake", "c1.clone", "public")
    assert str(inv.provider.operator_cidr) == f"{inside}/32"
    assert json.loads(out)["operator_cidr"] == f"{inside}/32"

    routes["identity.example.com"] = ip.IPv4Address("192.168.1.20")  # behind NAT: the cloud sees another
    code, _, err = run_ccrp_inprocess("init", "--provider", "openstack", "--cloud", "ccrp-fake", "-o", "nat.yaml",
                                      home=here / "home")
    assert code == 0, err
    text = (here / "nat.yaml").read_text()
    assert "operator_cidr: 203.0.113.0/24 # SSH to clones only from here: put your public address range" in text, text


def test_init_cloud_writes_nothing_a_cloud_could_inject_and_says_what_is_missing(here, fake_cloud):
    fake, _routes = fake_cloud
    fake.flavors.clear()
    code, _, err = run_ccrp_inprocess("init", "--provider", "openstack", "--cloud", "ccrp-fake", home=here / "home")
    assert code == 2 and "no public flavor a clone fits in" in err and err.count("\n") == 1, err
    fake.add_flavor("big\nprovider: {kind: docker}", vcpus=4, ram=8192, disk=40)  # a name that would add a key
    code, _, err = run_ccrp_inprocess("init", "--provider", "openstack", "--cloud", "ccrp-fake", home=here / "home")
    assert code == 2 and "answered a flavor that ccrp will not write" in err and err.count("\n") == 1, err
    for argv in (("--provider", "docker", "--cloud", "ccrp-fake"), ("--provider", "openstack", "--cloud", "a b")):
        code, _, err = run_ccrp_inprocess("init", *argv, home=here / "home")
        assert code == 2 and err.count("\n") == 1, (argv, err)
    assert not (here / "ccrp.yaml").exists()
