"""A ROS 2 (Jazzy) fleet (docs/ros2.md): what the inventory takes and refuses, and what the clone
and the robot get: a domain per robot, discovery only with the other end of the tunnel, RTPS only
through the tunnel, no master, and the watchdog's ROS 2 check."""

from __future__ import annotations

import shutil
import socket
import subprocess
from xml.etree import ElementTree

import pytest
import yaml

from ccrp_cli.ops import clones
from ccrp_cli.errors import InputError
from ccrp_cli.fleet import Fleet, clone_view
from ccrp_cli.loader import parse_inventory
from ccrp_cli.render import bundles, cloudinit, network
from ccrp_cli.services.registry import boots, image_agents
from ccrp_cli.providers import info
from tests.conftest import ROOT

JAZZY = ROOT / "inventories" / "lab-jazzy.yaml"


@pytest.fixture
def jazzy(ccrp_home):
    from ccrp_cli.ops import vpn

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
    (lambda d: d["ros"].update(distro="humble"), "ros.distro"),
])
def test_what_a_jazzy_fleet_cannot_have_yet_is_refused(change, expected):
    data = yaml.safe_load(JAZZY.read_text())
    change(data)
    with pytest.raises(InputError, match=expected):
        parse_inventory(data, "lab-jazzy.yaml")


@pytest.mark.parametrize("where, said", [
    ("robots", {"name": "nao1", "type": "nao", "ros": {"distro": "noetic"}}),
    ("types", {"nao": {"ros": {"distro": "humble"}}}),
    ("template", {"prefix": "robot", "ros": {"distro": "kilted"}}),
])
def test_a_robot_of_another_distro_than_its_fleet_is_refused_in_one_line(ccrp_home, tmp_path, where, said):
    """One distro per fleet, robots and clones alike: a robot (or type, or the template) saying it
    runs another ROS is refused by `fleet validate` in one line; saying the fleet's is fine."""
    from tests.conftest import run_ccrp

    data = yaml.safe_load(JAZZY.read_text())
    data[where] = [said] if where == "robots" else said
    path = tmp_path / "ccrp.yaml"
    path.write_text(yaml.safe_dump(data))
    proc = run_ccrp("fleet", "validate", "-i", str(path), home=ccrp_home)
    distro = said.get("ros", {}).get("distro") or said["nao"]["ros"]["distro"]
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert f"runs ROS {distro}, the fleet ros.distro jazzy: a fleet has one distro" in proc.stderr, proc.stderr
    same = yaml.safe_load(yaml.safe_dump(data).replace(f"distro: {distro}", "distro: jazzy"))
    assert parse_inventory(same, "same.yaml").ros.distro == "jazzy"


def test_a_jazzy_fleet_takes_the_api_manager_and_knowledge_sync():
    """As a Noetic fleet does (docs/services.md): no longer refused for ROS 2."""
    data = yaml.safe_load(JAZZY.read_text())
    data["services"] = {"api_manager": {"backend": "face-recognition"},
                        "knowledge": {"datasets": {"faces": {"robots": ["nao1", "nao2"]}}}}
    inv = parse_inventory(data, "lab-jazzy.yaml")
    assert inv.api_manager_of(inv.robots[0]).backend == "face-recognition"
    assert set(inv.datasets_of("nao1", ["nao1", "nao2"])) == {"faces"}


def test_a_jazzy_image_has_what_the_api_manager_needs_and_user_data_its_units(ccrp_home):
    """The image's venv has OpenCV (cv2.face, the cascades) and the Vision client, as Noetic's; the
    agent itself comes with its config (unit/test_api_manager.py), not in the image's files."""
    plat = cloudinit.platform("jazzy", "debian-bookworm")
    names = [p.split("==")[0] for p in plat.pip]
    assert {"opencv-contrib-python-headless", "google-cloud-vision"} <= set(names), names
    inv = Fleet.open(JAZZY).inventory
    written = {f["path"] for f in cloudinit.image_config(inv, image_agents())["write_files"]}
    assert not [p for p in written if p.endswith(".py")], written


@pytest.mark.skipif(shutil.which("cloud-init") is None, reason="cloud-init not installed (apt-get install cloud-init)")
# Kilted on AWS alone (the smallest user-data limit): its user-data differs from Jazzy's only in
# the recipe's names, and each schema check takes about 7 s here.
@pytest.mark.parametrize("kind, distro", [("aws", "jazzy"), ("gcp", "jazzy"), ("openstack", "jazzy"), ("aws", "kilted")])
def test_a_ros2_fleet_on_a_cloud_installs_the_wheels_venv_and_passes_cloud_init_schema(ccrp_home, tmp_path, kind, distro):
    """A cloud's image (`snapshot bake`'s builder, or a bare clone's first boot) gets the same venv as
    the Docker image: the recipe's wheels from the index, then ros2-setup writes its setup.sh. Each
    ROS 2 distro the same way, from its recipe."""
    from ccrp_cli.ops import vpn

    data = yaml.safe_load((ROOT / "inventories" / f"{kind}.yaml").read_text())
    data["ros"]["distro"] = distro
    path = tmp_path / "ccrp.yaml"
    path.write_text(yaml.safe_dump(data))
    fleet = Fleet.open(path)
    vpn.init(fleet)
    plat = cloudinit.platform(distro, fleet.inventory.clone_platform)
    venv = [["python3", "-m", "venv", f"/opt/ros/{distro}"],
            [f"/opt/ros/{distro}/bin/pip", "install", "--no-cache-dir", *plat.pip, "empy==3.3.4"],
            ["sh", "/usr/local/lib/ccrp/ros2-setup", f"/opt/ros/{distro}", distro]]
    view = clone_view(fleet, fleet.store.load_state(), fleet.inventory.robots[0].name)
    keys = ["ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFakeKeyForSchemaOnly operator"]
    texts = {"builder": cloudinit.builder_user_data(fleet.inventory, "0123456789abcdef", image_agents()),
             "bare": cloudinit.user_data(view, boots(), install_packages=True, login_keys=keys),
             "snapshot": cloudinit.user_data(view, boots(), login_keys=keys)}
    for what, text in texts.items():
        runcmd = yaml.safe_load(text)["runcmd"]
        assert all(step in runcmd for step in venv) == (what != "snapshot"), (what, runcmd)
        if what != "builder":  # a VM clone, its own kernel: ROS 2's receive buffers from its first boot
            sysctl = next(f for f in yaml.safe_load(text)["write_files"] if f["path"] == cloudinit.ROS2_SYSCTL)
            assert "net.core.rmem_default = 4194304" in sysctl["content"], sysctl
            assert next(c for c in runcmd if c[-1] == cloudinit.ROS2_SYSCTL)[:3] == ["sh", "-c", 'sysctl -q -p "$0" || '
                                                                                   'echo "ccrp: $0 not applied (no kernel of its own?)"']
        assert plat.pip[0] not in text or what != "snapshot"
        info(kind).fit_user_data(text)
        f = tmp_path / f"{what}.yaml"
        f.write_text(text)
        proc = subprocess.run(["cloud-init", "schema", "--config-file", str(f)], capture_output=True, text=True)
        assert proc.returncode == 0 and "Valid cloud-config" in proc.stdout, what + proc.stdout + proc.stderr
    # The bake proves the venv's packages, not the system python's.
    proof = next(c for c in yaml.safe_load(texts["builder"])["runcmd"] if "pip-ok" in " ".join(c))
    python = f"/opt/ros/{distro}/bin/python"
    assert proof[proof.index(python):][:5] == [python, "-m", "pip", "show", f"ros-{distro}-rclpy"], proof


@pytest.mark.skipif(shutil.which("cloud-init") is None, reason="cloud-init not installed (apt-get install cloud-init)")
@pytest.mark.parametrize("distro", ["jazzy", "kilted"])
@pytest.mark.parametrize("kind", ["aws", "gcp", "openstack"])
def test_an_image_with_its_own_ros2_gets_no_venv_and_passes_cloud_init_schema(ccrp_home, tmp_path, kind, distro):
    """`ros.platform: ubuntu-noble-ros`: the base image has ROS 2 under /opt/ros/<distro> (apt).
    Its builder and a bare clone write nothing over that prefix (no venv, no setup.sh of ours): the
    agents' packages go to the system python, /opt/ros/jazzy/bin/python becomes a launcher only where
    none is, and the bake proves the image's ROS as the agents start it."""
    from ccrp_cli.ops import vpn

    data = yaml.safe_load((ROOT / "inventories" / f"{kind}.yaml").read_text())
    data["ros"] = {"distro": distro, "platform": "ubuntu-noble-ros"}
    path = tmp_path / "ccrp.yaml"
    path.write_text(yaml.safe_dump(data))
    fleet = Fleet.open(path)
    vpn.init(fleet)
    plat = cloudinit.platform(distro, "ubuntu-noble-ros")
    assert plat.ros_installed and f"ros-{distro}-ros-base" in plat.packages and "python3-venv" not in plat.packages
    view = clone_view(fleet, fleet.store.load_state(), fleet.inventory.robots[0].name)
    keys = ["ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIFakeKeyForSchemaOnly operator"]
    texts = {"builder": cloudinit.builder_user_data(fleet.inventory, "0123456789abcdef", image_agents()),
             "bare": cloudinit.user_data(view, boots(), install_packages=True, login_keys=keys)}
    launcher = ["sh", "-c", '[ -e "$0/bin/python" ] || ln -s "$1" "$0/bin/python"', f"/opt/ros/{distro}",
                "/usr/local/lib/ccrp/ros-python"]
    for what, text in texts.items():
        data = yaml.safe_load(text)
        runcmd = data["runcmd"]
        assert not [c for c in runcmd if "venv" in c or any("ros2-setup" in a for a in c)], (what, runcmd)
        assert not [f["path"] for f in data["write_files"] if f["path"].startswith("/opt/ros")], what
        assert ["env", "PIP_BREAK_SYSTEM_PACKAGES=1", "pip3", "install", "--no-cache-dir", *plat.pip] in runcmd, runcmd
        assert launcher in runcmd and runcmd.index(launcher) > runcmd.index(["env", "PIP_BREAK_SYSTEM_PACKAGES=1", "pip3",
                                                                              "install", "--no-cache-dir", *plat.pip])
        assert f"ros-{distro}-ros-base" in data["packages"]
        info(kind).fit_user_data(text)
        f = tmp_path / f"{what}.yaml"
        f.write_text(text)
        proc = subprocess.run(["cloud-init", "schema", "--config-file", str(f)], capture_output=True, text=True)
        assert proc.returncode == 0 and "Valid cloud-config" in proc.stdout, what + proc.stdout + proc.stderr
    assert cloudinit.bake_proofs(fleet.inventory) == ["apt", "locale", "pip", "ros"]
    proof = next(c for c in yaml.safe_load(texts["builder"])["runcmd"] if "ros-ok" in " ".join(c))
    assert proof[4:6] == [f"/opt/ros/{distro}/bin/python", "-c"] and "import rclpy, zenoh, cv2" in proof[6], proof


def test_the_launcher_runs_the_system_python_in_the_distros_own_setup(tmp_path):
    """templates/image/ros-python, linked as <prefix>/bin/python: <prefix>/setup.sh is sourced (the
    prefix is the link's), then python3 runs with the arguments."""
    prefix = tmp_path / "opt" / "ros" / "jazzy"
    (prefix / "bin").mkdir(parents=True)
    (prefix / "setup.sh").write_text('export CCRP_SEEN_SETUP="$AMENT_PREFIX_PATH:sourced"\n')
    launcher = tmp_path / "ros-python"  # installed 0755 by cloud-init (write_files)
    launcher.write_text((ROOT / "templates" / "image" / "ros-python").read_text())
    launcher.chmod(0o755)
    (prefix / "bin" / "python").symlink_to(launcher)
    proc = subprocess.run([str(prefix / "bin" / "python"), "-c", "import os, sys; print(os.environ['CCRP_SEEN_SETUP'], sys.argv[1])",
                           "arg"], capture_output=True, text=True, env={"PATH": "/usr/bin:/bin", "AMENT_PREFIX_PATH": "x"})
    assert proc.returncode == 0 and proc.stdout.split() == ["x:sourced", "arg"], proc.stderr


def test_the_own_ros2_platform_is_refused_on_docker_and_without_a_base_image(ccrp_home, tmp_path):
    from ccrp_cli.ops import snapshots

    data = yaml.safe_load(JAZZY.read_text())
    data["ros"]["platform"] = "ubuntu-noble-ros"
    with pytest.raises(InputError, match="ros.platform ubuntu-noble-ros is for clouds"):
        parse_inventory(data, "lab-jazzy.yaml")
    data["ros"]["platform"] = "ubuntu-jammy"
    with pytest.raises(InputError, match="not one of ros.distro jazzy's"):
        parse_inventory(data, "lab-jazzy.yaml")
    cloud = yaml.safe_load((ROOT / "inventories" / "aws.yaml").read_text())
    cloud["ros"] = {"distro": "jazzy", "platform": "ubuntu-noble-ros"}
    path = tmp_path / "ccrp.yaml"
    path.write_text(yaml.safe_dump(cloud))
    fleet = Fleet.open(path)
    # No provider call is made before the refusal: the stock Debian image has no ROS 2 to use.
    with pytest.raises(InputError, match="bakes from your image with ROS jazzy installed") as err:
        snapshots.bake(fleet, None, lambda msg: None)
    assert "--base-image" in err.value.hint


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


def test_a_jazzy_clone_runs_no_master_and_rclpy_agents(jazzy):
    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    data = cloudinit.user_data_dict(view, boots())
    starts = [c[2:] for c in data["runcmd"] if c[:2] == ["systemctl", "start"]]
    assert starts[0] == ["ccrp-power.socket"]  # alone and first (unit/test_power_device.py)
    enabled = starts[1]
    assert enabled == ["ccrp-firewall.service", "ccrp-openvpn.service", "ccrp-graph.service", "ccrp-relay.service",
                       "ccrp-autostop.service", "ccrp-power.service", "ccrp-api-manager.service", "ccrp-knowledge.service"]
    paths = {f["path"] for f in data["write_files"]}
    assert "/usr/local/lib/ccrp/ros2_graph.py" in paths and "/etc/systemd/system/ccrp-rosmaster.service" not in paths
    # The graph keeper in the master's place, as a user of its own: not `ros`, whose nodes it reports on.
    assert "/etc/systemd/system/ccrp-graph.service" in paths
    assert {"ccrp-graph", "ros"} <= {u["name"] for u in data["users"]}
    assert cloudinit.ROS2_SYSCTL not in paths  # a container shares the host's kernel: `ccrp doctor` says so
    # The relay comes with the user-data (the API manager is in the image, the knowledge agent is
    # pushed by fleet up).
    assert {"/usr/local/lib/ccrp/relay.py", "/usr/local/lib/ccrp/relay_ros2.py"} <= paths
    assert "/usr/local/lib/ccrp/api_manager.py" not in paths
    # Its loader of the workspace's message types is fleet up's to push (a ROS 2 clone's only).
    from ccrp_cli.services.base import ServiceContext
    from ccrp_cli.services.sharing import Relay

    assert "/usr/local/lib/ccrp/relay_interfaces.py" not in paths
    pushed = {f.dest: f.content for f in Relay().files(ServiceContext(jazzy, jazzy.store.load_state(), jazzy.inventory.robots[1]))}
    assert pushed["/usr/local/lib/ccrp/relay_interfaces.py"] == (ROOT / "ccrp_cli/agent/relay_interfaces.py").read_text()
    from ccrp_cli.ops import vpn

    fleet, state, robot = _noetic(jazzy)
    vpn.init(fleet)
    assert [f.name for f in Relay().files(ServiceContext(fleet, state, fleet.inventory.robots[0]))] == ["relay.json"]
    # Both new units run their agent in the clone's ROS environment, as the relay's does: ros-run
    # sources the distro's setup.sh, which puts the venv (rclpy, cv2, Zenoh) on python3's path.
    units = {f["path"].rsplit("/", 1)[1]: f["content"] for f in data["write_files"] if f["path"].endswith(".service")}
    for unit in ("ccrp-api-manager.service", "ccrp-knowledge.service"):
        assert "EnvironmentFile=/etc/ccrp/ros.env" in units[unit]
        assert "ExecStart=/usr/local/lib/ccrp/ros-run /usr/bin/python3 " in units[unit], units[unit]
    assert clones.serving_port(jazzy.inventory) == "ros2"


def test_the_edge_bundle_of_a_jazzy_robot(jazzy):
    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    files = {f.name: f.content for f in bundles.edge_bundle(view, jazzy.pki.credentials("nao2"), "203.0.113.10")}
    watchdog = _env(files["watchdog.env"].strip())
    assert watchdog["CCRP_WATCHDOG_CHECK"] == "icmp" and watchdog["CCRP_CLONE_HOST"] == str(view.addr.clone_vpn_ip)
    assert "CCRP_MASTER_PORT" not in watchdog
    env = _env(files["ros.env"])
    assert env["ROS_STATIC_PEERS"] == str(view.addr.clone_vpn_ip)
    # Its participants announce its VPN address and loopback, whatever the tunnel was when they
    # started; both Fast DDS 2's and 3's variables name the profile the bundle installs.
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == env["FASTDDS_DEFAULT_PROFILES_FILE"] == network.ROBOT_FASTDDS_PROFILE
    assert f'"$here/fastdds.xml" "$root{network.ROBOT_FASTDDS_PROFILE}"' in files["install.sh"]
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    rtps = ElementTree.fromstring(files["fastdds.xml"].encode()).find("f:participant[@is_default_profile='true']/f:rtps", ns)
    for where in ("f:builtin/f:metatrafficUnicastLocatorList", "f:defaultUnicastLocatorList"):
        assert [a.text for a in rtps.findall(f"{where}/f:locator/f:udpv4/f:address", ns)] == \
            [str(view.addr.robot_vpn_ip), "127.0.0.1"], where
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


def test_health_asks_the_graph_keeper_and_says_when_it_does_not_answer_or_answers_oddly(tmp_path, monkeypatch):
    """ccrp-graph.service's answer is what status shows of a ROS 2 clone's graph: a remote node as
    the robot's, a local one as the clone's. No keeper listening, or an answer not of its shape,
    make the graph unreachable, with why."""
    import json
    import socket
    import threading

    from ccrp_cli.agent import health

    unit, path = tmp_path / "ccrp-graph.service", str(tmp_path / "graph.sock")
    unit.write_text("[Unit]\n")
    monkeypatch.setattr(health, "GRAPH_UNIT", str(unit))
    monkeypatch.setattr(health, "GRAPH_SOCKET", path)
    monkeypatch.setattr(health.socket, "gethostname", lambda: "cri-nao1")
    env = {"ROS_DISTRO": "jazzy", "CCRP_ROBOT": "nao1"}
    assert health.graph(env)["error"] == "ccrp-graph.service did not answer (FileNotFoundError)"

    def keeper(answers):
        server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        server.bind(path)
        server.listen(1)

        def run():
            with server:
                for answer in answers:
                    conn, _ = server.accept()
                    with conn:
                        conn.sendall(answer.encode())
        thread = threading.Thread(target=run, daemon=True)
        thread.start()
        return thread

    good = json.dumps({"reachable": True, "nodes": {"/nao1_demo": "remote", "/ccrp_relay": "local"},
                       "published_topics": ["/chatter"]})
    odd = ['{"nodes": {}}', "[1]", "{", json.dumps({"nodes": ["/a"], "published_topics": []})]
    thread = keeper([good, *odd])
    assert health.graph(env) == {"reachable": True, "published_topics": ["/chatter"],
                                 "nodes": {"/nao1_demo": "ros2://nao1/", "/ccrp_relay": "ros2://cri-nao1/"}}
    for answer in odd:
        got = health.graph(env)
        assert got["reachable"] is False and got["nodes"] == {} and "did not answer" in got["error"], answer
    thread.join(5)


def test_a_node_not_named_yet_is_not_the_robots():
    """An endpoint discovered before its participant's node names (rmw's `_NODE_NAME_UNKNOWN_`) is
    no node yet: run 43's `robot sim --wait` on the Jazzy OpenStack scenario took it for the robot's."""
    from ccrp_cli.probe import robot_link

    h = {"vpn": {"clients": [{"cn": "nao1", "real_address": "203.0.113.5:40000"}]},
         "master": {"nodes": {"/_NODE_NAME_UNKNOWN_": "ros2://nao1/", "/ccrp_relay": "ros2://cri-nao1/"}}}
    assert robot_link(h, "nao1")[1] == []
    h["master"]["nodes"]["/nao1_demo"] = "ros2://nao1/"
    assert robot_link(h, "nao1")[1] == ["/nao1_demo"]


def test_a_ros2_clone_whose_graph_does_not_answer_is_named_so():
    from ccrp_cli.alerts import clone_alerts
    from ccrp_cli.models.status import StatusRow

    row = dict(robot="nao1", clone="cri-nao1", phase="ready", status="running", state="running", common_ip="10.90.0.10",
               vpn_subnet="10.80.1.0/24", secrets=True, master_reachable=False, vpn_connected=True)
    assert "ROS master of nao1's clone" in clone_alerts(StatusRow(**row, ros_distro="noetic"))[0]["text"]
    assert "ROS 2 graph of nao1's clone" in clone_alerts(StatusRow(**row, ros_distro="jazzy"))[0]["text"]


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

    transport = property(lambda self: self)  # a fake clone is its own transport
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
    from ccrp_cli.robot import evaluation

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


def test_a_robot_with_its_own_ros2_at_another_prefix_needs_only_the_bundles_env_and_guard(jazzy, tmp_path):
    """A real robot's ROS 2 is its own (an apt install, a source build under its home...): the edge
    bundle brings nothing of the wheels. Installed (under a staging root), its profile script gives a
    shell whose own ROS 2 lives at another prefix the robot's domain, range, peer and RMW, and keeps
    that install's paths; the RTPS guard fences by ports and addresses alone, whatever the prefix
    (run here with a stand-in iptables that records its calls)."""
    view = clone_view(jazzy, jazzy.store.load_state(), "nao2")
    files = bundles.edge_bundle(view, jazzy.pki.credentials("nao2"), "203.0.113.10")
    files_by_name = {f.name: f.content for f in files}
    assert not [f.name for f in files if "ros-jazzy-" in f.content or "/opt/ros/jazzy" in f.content]
    out = bundles.write_bundle(tmp_path / "bundle", files, {"robot": "nao2"})
    root = tmp_path / "root"
    path = "/usr/bin:/bin:/usr/sbin:/sbin"
    assert subprocess.run(["sh", str(out / "install.sh")], env={"CCRP_ROOT": str(root), "PATH": path},
                          capture_output=True).returncode == 0
    # The robot's own install, elsewhere than /opt/ros/<distro> (which does not exist here).
    own = tmp_path / "home" / "nao" / "ros2_jazzy" / "install"
    own.mkdir(parents=True)
    (own / "setup.sh").write_text(f'export AMENT_PREFIX_PATH={own}\nexport LD_LIBRARY_PATH={own}/lib\n')
    profile = (root / "etc/profile.d/ccrp-ros.sh").read_text().replace("/etc/ccrp/", f"{root}/etc/ccrp/")
    (tmp_path / "profile.sh").write_text(profile)
    shown = subprocess.run(["sh", "-c", f'. "{own}/setup.sh"; . "{tmp_path}/profile.sh"; env'], env={"PATH": path},
                           capture_output=True, text=True)
    env = dict(line.split("=", 1) for line in shown.stdout.splitlines() if "=" in line)
    assert (env["ROS_DISTRO"], env["ROS_DOMAIN_ID"], env["ROS_AUTOMATIC_DISCOVERY_RANGE"], env["RMW_IMPLEMENTATION"]) == \
        ("jazzy", str(network.ros_domain(view.addr.index)), "LOCALHOST", "rmw_fastrtps_cpp"), env
    assert env["ROS_STATIC_PEERS"] == str(view.addr.clone_vpn_ip)
    assert env["FASTDDS_DEFAULT_PROFILES_FILE"] == network.ROBOT_FASTDDS_PROFILE
    assert (root / network.ROBOT_FASTDDS_PROFILE.lstrip("/")).read_text() == files_by_name["fastdds.xml"]
    assert env["AMENT_PREFIX_PATH"] == str(own) and env["LD_LIBRARY_PATH"] == f"{own}/lib"
    # The guard: a stand-in iptables and getent; its files under the staging root.
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "calls"
    (bin_dir / "iptables").write_text(f'#!/bin/sh\necho "$*" >> {calls}\ncase "$*" in *" -C "*) exit 1;; esac\n')
    (bin_dir / "getent").write_text("#!/bin/sh\necho '203.0.113.10 STREAM x'\n")
    for tool in ("iptables", "getent"):
        (bin_dir / tool).chmod(0o755)
    guard = (root / "usr/local/lib/ccrp/ccrp-rtps-guard").read_text()
    guard = guard.replace("/etc/ccrp/", f"{root}/etc/ccrp/").replace("/run/ccrp", f"{tmp_path}/run")
    (tmp_path / "guard").write_text(guard)
    proc = subprocess.run(["sh", str(tmp_path / "guard"), "up"], env={"PATH": f"{bin_dir}:/usr/bin:/bin"},
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lo, hi = network.rtps_ports(view.addr.index)
    inserted = [line for line in calls.read_text().splitlines() if line.startswith("-w -I OUTPUT")]
    assert inserted == [f"-w -I OUTPUT -p udp --dport {lo}:{hi} -j CCRP-RTPS", "-w -I OUTPUT -p udp -d 239.255.0.1 -j CCRP-RTPS",
                        "-w -I OUTPUT -p udp -d 203.0.113.10 ! --dport 1194 -j CCRP-RTPS"], calls.read_text()
    chain = [line for line in calls.read_text().splitlines() if line.startswith("-w -A CCRP-RTPS")]
    assert chain == ["-w -A CCRP-RTPS -o lo -j RETURN", "-w -A CCRP-RTPS -o ccrpvpn -j RETURN", "-w -A CCRP-RTPS -j DROP"]


def test_doctor_names_the_hosts_receive_buffer_for_ros2_clones_on_docker(tmp_path):
    from ccrp_cli.ops import doctor

    f = tmp_path / "rmem_default"
    f.write_text("212992\n")
    low = doctor.host_receive_buffer(str(f))
    assert low.status == doctor.WARN and "sysctl -w net.core.rmem_default=4194304" in low.hint
    f.write_text("4194304\n")
    assert doctor.host_receive_buffer(str(f)).status == doctor.OK
    assert doctor.host_receive_buffer(str(tmp_path / "none")).status == doctor.SKIP
