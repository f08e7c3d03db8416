"""A ROS 2 (Jazzy) fleet (docs/ros2.md): what the inventory takes and refuses, and what the clone
and the robot get: a domain per robot, discovery only with the other end of the tunnel, RTPS only
through the tunnel, no master, and the watchdog's ROS 2 check."""

from __future__ import annotations

import shutil
import socket
import subprocess

import pytest
import yaml

from ccrp_cli import clones
from ccrp_cli.errors import InputError
from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.loader import parse_inventory
from ccrp_cli.render import bundles, cloudinit, network
from ccrp_cli.render.limits import fit_user_data
from tests.conftest import ROOT

JAZZY = ROOT / "inventories" / "lab-jazzy.yaml"


@pytest.fixture
def jazzy(ccrp_home):
    from ccrp_cli import vpn

    fleet = Fleet.open(JAZZY)
    vpn.init(fleet)
    vpn.issue(fleet, "nao2")
    return fleet


def _env(text: str) -> dict[str, str]:
    return dict(line.split("=", 1) for line in text.splitlines())


def test_lab_jazzy_is_the_thesis_lab_on_jazzy():
    data = yaml.safe_load(JAZZY.read_text())
    inv = parse_inventory(data, "lab-jazzy.yaml")
    assert inv.ros.distro == "jazzy" and inv.ros.ros2 and [r.name for r in inv.robots] == ["nao1", "nao2", "turtlebot1"]


@pytest.mark.parametrize("change, expected", [
    (lambda d: d.update(services={"api_manager": {}}), "services.api_manager is ROS 1 only"),
    (lambda d: d["ros"].update(distro="humble"), "ros.distro"),
    (lambda d: d.update(services={"knowledge": {"datasets": {"faces": {"robots": ["nao1", "nao2"]}}}}),
     "services.knowledge is not built into"),
])
def test_what_a_jazzy_fleet_cannot_have_yet_is_refused(change, expected):
    data = yaml.safe_load(JAZZY.read_text())
    change(data)
    with pytest.raises(InputError, match=expected):
        parse_inventory(data, "lab-jazzy.yaml")


@pytest.mark.skipif(shutil.which("cloud-init") is None, reason="cloud-init not installed (apt-get install cloud-init)")
@pytest.mark.parametrize("kind", ["aws", "gcp", "openstack"])
def test_a_jazzy_fleet_on_a_cloud_installs_the_wheels_venv_and_passes_cloud_init_schema(ccrp_home, tmp_path, kind):
    """A cloud's image (`snapshot bake`'s builder, or a bare clone's first boot) gets the same venv as
    the Docker image: the recipe's wheels from the index, then ros2-setup writes its setup.sh."""
    from ccrp_cli import vpn

    data = yaml.safe_load((ROOT / "inventories" / f"{kind}.yaml").read_text())
    data["ros"]["distro"] = "jazzy"
    path = tmp_path / "ccrp.yaml"
    path.write_text(yaml.safe_dump(data))
    fleet = Fleet.open(path)
    vpn.init(fleet)
    plat = cloudinit.platform("jazzy", kind)
    venv = [["python3", "-m", "venv", "/opt/ros/jazzy"],
            ["/opt/ros/jazzy/bin/pip", "install", "--no-cache-dir", *plat.pip, "empy==3.3.4"],
            ["sh", "/usr/local/lib/ccrp/ros2-setup", "/opt/ros/jazzy", "jazzy"]]
    view = clone_view(fleet, fleet.store.load_state(), fleet.inventory.robots[0].name)
    keys = ["ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFakeKeyForSchemaOnly operator"]
    texts = {"builder": cloudinit.builder_user_data(fleet.inventory, "0123456789abcdef"),
             "bare": cloudinit.user_data(view, install_packages=True, login_keys=keys),
             "snapshot": cloudinit.user_data(view, login_keys=keys)}
    for what, text in texts.items():
        runcmd = yaml.safe_load(text)["runcmd"]
        assert all(step in runcmd for step in venv) == (what != "snapshot"), (what, runcmd)
        assert "ros-jazzy-rclpy==7.1.6" not in text or what != "snapshot"
        fit_user_data(kind, text)
        f = tmp_path / f"{what}.yaml"
        f.write_text(text)
        proc = subprocess.run(["cloud-init", "schema", "--config-file", str(f)], capture_output=True, text=True)
        assert proc.returncode == 0 and "Valid cloud-config" in proc.stdout, what + proc.stdout + proc.stderr
    # The bake proves the venv's packages, not the system python's.
    proof = next(c for c in yaml.safe_load(texts["builder"])["runcmd"] if "pip-ok" in " ".join(c))
    assert proof[proof.index("/opt/ros/jazzy/bin/python"):][:5] == ["/opt/ros/jazzy/bin/python", "-m", "pip", "show",
                                                                    "ros-jazzy-rclpy"], proof


def test_domain_comes_from_the_slot_and_stays_below_the_ephemeral_ports():
    assert [network.ros_domain(k) for k in (1, 2, 100, 101, 255)] == [1, 2, 100, 1, 55]
    assert network.rtps_ports(1) == (7650, 7899)
    assert max(network.rtps_ports(k)[1] for k in range(1, 256)) < 32768


def test_each_end_names_the_other_as_its_only_peer_in_the_robots_domain(jazzy):
    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    clone, robot = _env(network.ros_env(view, "clone")), _env(network.ros_env(view, "robot"))
    assert view.addr.index == 2
    assert clone["ROS_STATIC_PEERS"] == str(view.addr.robot_vpn_ip) and robot["ROS_STATIC_PEERS"] == str(view.addr.clone_vpn_ip)
    for env in (clone, robot):
        assert env["ROS_DOMAIN_ID"] == "2" and env["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
        assert env["ROS_DISTRO"] == "jazzy" and env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
        assert "ROS_MASTER_URI" not in env and env["CCRP_ROBOT"] == "nao2"


def test_rtps_leaves_the_clone_only_through_the_tunnel(jazzy):
    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    fw4, fw6 = network.firewall_rules(view)
    out4 = [ln for ln in fw4.splitlines() if ln.startswith("-A OUTPUT")]
    assert out4 == ["-A OUTPUT -o lo -j ACCEPT", "-A OUTPUT -o ccrpvpn -j ACCEPT",
                    "-A OUTPUT -m conntrack --ctstate ESTABLISHED,RELATED -j ACCEPT",
                    "-A OUTPUT -p udp -m multiport --dports 53,123 -j ACCEPT", "-A OUTPUT -p udp -j DROP"]
    assert "-A OUTPUT -p udp -j DROP" in fw6 and "-o ccrpvpn" not in fw6
    # Inbound, RTPS comes only from the tunnel, as any ROS traffic (the rules ROS 1 has).
    assert f"-A INPUT -i ccrpvpn -s {view.addr.robot_vpn_ip} -j ACCEPT" in fw4
    noetic = clone_view(*_noetic(jazzy))
    assert "-A OUTPUT" not in network.firewall_rules(noetic)[0]


def _noetic(jazzy):
    from tests.conftest import LAB

    fleet = Fleet.open(LAB)
    return fleet, fleet.store.load_state(), "nao1"


def test_a_jazzy_clone_runs_no_master_or_api_manager_and_an_rclpy_relay(jazzy):
    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    data = cloudinit.user_data_dict(view)
    starts = [c[3:] for c in data["runcmd"] if c[:3] == ["systemctl", "enable", "--now"]]
    assert starts[0] == ["ccrp-power.socket"]  # alone and first (unit/test_power_device.py)
    enabled = starts[1]
    assert enabled == ["ccrp-firewall.service", "ccrp-openvpn.service", "ccrp-relay.service", "ccrp-autostop.service",
                       "ccrp-power.service"]
    paths = {f["path"] for f in data["write_files"]}
    assert "/usr/local/lib/ccrp/ros2_graph.py" in paths and "/etc/systemd/system/ccrp-rosmaster.service" not in paths
    # The image holds no agents (only the wheels' venv): the relay comes with the user-data.
    assert {"/usr/local/lib/ccrp/relay.py", "/usr/local/lib/ccrp/relay_ros2.py"} <= paths
    assert clones.serving_port(jazzy.inventory) == "ros2"


def test_the_edge_bundle_of_a_jazzy_robot(jazzy):
    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    files = {f.name: f.content for f in bundles.edge_bundle(view, jazzy.pki.credentials("nao2"), "203.0.113.10")}
    watchdog = _env(files["watchdog.env"].strip())
    assert watchdog["CCRP_WATCHDOG_CHECK"] == "icmp" and watchdog["CCRP_CLONE_HOST"] == str(view.addr.clone_vpn_ip)
    assert "CCRP_MASTER_PORT" not in watchdog
    assert _env(files["ros.env"])["ROS_STATIC_PEERS"] == str(view.addr.clone_vpn_ip)
    assert "/opt/ros/${ROS_DISTRO}/setup.sh" in files["ccrp-ros.sh"]
    guard = files["ccrp-rtps-guard"]
    assert '-p udp --dport 7900:8149\n-p udp -d 239.255.0.1"' in guard and '! --dport ${2:-1194}' in guard
    assert "ccrp-rtps-guard.service" in files and "enable --now $units" in files["install.sh"]


def _watchdog():
    import importlib.machinery
    import importlib.util

    path = str(ROOT / "templates" / "edge" / "ccrp-watchdog")
    loader = importlib.machinery.SourceFileLoader("ccrp_watchdog", path)
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader("ccrp_watchdog", loader))
    loader.exec_module(module)
    return module


def test_watchdog_icmp_check_answers_for_loopback_and_not_for_a_silent_address():
    watchdog = _watchdog()
    try:
        socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_ICMP).close()
    except PermissionError:
        pytest.skip("raw ICMP sockets need root (the watchdog runs as root on the robot)")
    assert watchdog.echo_answered("127.0.0.1", 7, 1.0) is True
    assert watchdog.echo_answered("203.0.113.1", 8, 0.3) is False  # TEST-NET-3: nobody answers


def test_a_ros2_clone_whose_graph_does_not_answer_is_named_so():
    from ccrp_cli.alerts import clone_alerts

    row = {"robot": "nao1", "status": "running", "secrets": True, "master_reachable": False, "vpn_connected": True}
    assert "ROS master of nao1's clone" in clone_alerts(row)[0]["text"]
    assert "ROS 2 graph of nao1's clone" in clone_alerts(row | {"ros_distro": "jazzy"})[0]["text"]


class _Ends:
    """Both ends of the bench, faked: the simulated robot (Sims) and its clone (the provider),
    answering the agent's roles as it prints them."""

    def __init__(self, fleet, provider=None):
        self.clones, self.ran, self.pushed = self, [], []

    def running(self, robot):
        return True

    def query(self):
        return {"nao2": object()}

    def push(self, robot, files):
        self.pushed.append(("robot", [f.dest for f in files]))

    def push_files(self, robot, files, restart=()):
        self.pushed.append(("clone", [f.dest for f in files]))

    def exec(self, robot, argv, timeout=60):
        import json

        self.ran.append(argv)
        if "ping" in argv or "client" in argv:
            return 0, "rclpy noise\n" + json.dumps({"samples_ms": [1.0, 2.0, 3.0], "lost": 0}) + "\n"
        return 0, ""

    def clone_address(self, robot):
        return "203.0.113.7"

    def link(self, robot):
        return None


def test_bench_runs_on_a_ros2_fleet_with_the_same_agent(jazzy, monkeypatch):
    """`ccrp bench` refused a ROS 2 fleet (its agent was rospy only). Now the same agent runs on
    both ends in the machine's ROS environment (it takes rclpy where ros.env names no master), its
    clone units with a runtime directory for ROS logs: rclpy cannot start without one."""
    from ccrp_cli import evaluation

    ends = _Ends(jazzy)
    monkeypatch.setattr(evaluation, "Sims", lambda fleet: ends)
    rows = evaluation.rtt(jazzy, "nao2", samples=3)
    assert [(r["probe"], r["samples"]) for r in rows] == [("icmp", 3), ("icmp", 3), ("ros topic", 3)], rows
    assert ("robot", [evaluation.AGENT]) in ends.pushed and ("clone", [evaluation.AGENT]) in ends.pushed
    (unit,) = [a for a in ends.ran if a[0] == "systemd-run"]
    assert unit[unit.index(evaluation.IN_ROS[0]):] == [*evaluation.IN_ROS, "serve"]
    options = unit[:unit.index(evaluation.IN_ROS[0])]
    assert "RuntimeDirectory=ccrp-bench-serve" in options and "HOME=/run/ccrp-bench-serve" in options, options
    client = next(a for a in ends.ran if "client" in a)
    assert client[:len(evaluation.IN_ROS)] == evaluation.IN_ROS


def test_a_jazzy_edge_bundle_installs_its_guard_under_a_staging_root(jazzy, tmp_path):
    import subprocess

    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    out = bundles.write_bundle(tmp_path / "bundle", bundles.edge_bundle(view, jazzy.pki.credentials("nao2"),
                                                                        "203.0.113.10"), {"robot": "nao2"})
    root = tmp_path / "root"
    proc = subprocess.run(["sh", str(out / "install.sh")], env={"CCRP_ROOT": str(root), "PATH": "/usr/bin:/bin:/usr/sbin:/sbin"},
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert (root / "usr/local/lib/ccrp/ccrp-rtps-guard").stat().st_mode & 0o777 == 0o755
    assert (root / "etc/systemd/system/ccrp-rtps-guard.service").exists()
    assert subprocess.run(["sh", "-n", str(root / "usr/local/lib/ccrp/ccrp-rtps-guard")]).returncode == 0
    assert subprocess.run(["sh", str(root / "usr/local/lib/ccrp/ccrp-rtps-guard"), "sideways"],
                          capture_output=True).returncode == 2
