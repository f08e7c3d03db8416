"""End to end on Docker: ROS 2 Jazzy from the ros-jazzy-* wheels on the clones' Debian 12, and
DDS discovery confined to unicast static peers (docs/ros2.md).

Takes the run's Jazzy clone image (snapshots/jazzy.yaml: the recipe's packages and the
ros-jazzy-* wheels in the venv at /opt/ros/jazzy, fetch_wheels; built once a run for every Jazzy
fleet, tests/conftest.py clone_images) with tcpdump added for the capture, starts two containers of
it (no systemd: a sleep) on a Docker network of its own and runs a publisher of /chatter in one and
a subscriber in the other, each container capturing the UDP it sends and receives:

  1. ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST and ROS_STATIC_PEERS=<the other's address>: the
     subscriber gets the messages; no multicast packet in either capture, and no packet to or
     from anyone but the two of them.
  2. LOCALHOST without static peers: nothing arrives and nothing is sent (the range alone keeps a
     node to its own machine).
  3. The control: Jazzy's default range (SUBNET) does send RTPS multicast to 239.255.0.1, and the
     same capture counts it, so the zeros of 1 are not a capture that sees nothing.

The image, the network and the containers are removed at the end, whatever happens.
"""

from __future__ import annotations

import secrets
from concurrent.futures import ThreadPoolExecutor

import pytest

from ccrp_cli.providers.docker import images

docker = pytest.importorskip("docker", reason="the Docker SDK (`pip install docker`) is not installed")

pytestmark = [pytest.mark.slow]

DISTRO = "jazzy"
PYTHON = f"/opt/ros/{DISTRO}/bin/python"
DOMAIN = "17"  # a robot's domain: RTPS ports 7400 + 250 * 17 and up
LABELS = {"ccrp-test": "ros2-discovery"}

# One node: `pub SECONDS` publishes /chatter at 10 Hz for SECONDS; `sub WANT TIMEOUT` waits for
# WANT messages and prints how many came (exit 0 if all).
NODE = r"""
import sys, time
import rclpy
from std_msgs.msg import String

role, a, b = sys.argv[1], float(sys.argv[2]), float(sys.argv[3] if len(sys.argv) > 3 else 0)
rclpy.init()
node = rclpy.create_node("ccrp_" + role)
if role == "pub":
    pub, i, end = node.create_publisher(String, "/chatter", 10), 0, time.monotonic() + a
    while time.monotonic() < end:
        pub.publish(String(data=f"hello {i}"))
        i += 1
        rclpy.spin_once(node, timeout_sec=0.1)
    print(f"published {i}")
else:
    got, t0 = [], time.monotonic()
    node.create_subscription(String, "/chatter", lambda m: got.append(m.data), 10)
    while len(got) < a and time.monotonic() < t0 + b:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(f"received {len(got)} in {time.monotonic() - t0:.1f} s")
    sys.exit(0 if len(got) >= a else 1)
"""


@pytest.fixture(scope="module")
def client():
    try:
        c = docker.from_env(timeout=300)
        c.ping()
    except Exception as exc:  # noqa: BLE001 - any reason the engine does not answer
        pytest.skip(f"needs a running Docker engine ({exc})")
    try:
        c.images.get(images.DEFAULT_BASE)
    except docker.errors.ImageNotFound:
        pytest.skip(f"needs the base image {images.DEFAULT_BASE} (`ccrp snapshot build` on a Docker fleet makes it)")
    return c


# tcpdump on the run's clone image: one layer over it. A Jazzy image of its own (tcpdump among its
# packages) installed the recipe's packages and the venv again each run.
CAPTURE_LAYER = """FROM {image}
RUN apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends tcpdump \\
 && rm -rf /var/lib/apt/lists/*
"""


@pytest.fixture(scope="module")
def pair(client, clone_images):
    """Two containers of the Jazzy image on a network of their own: ((container, address), ...)."""
    from tests.scenarios.backend import free_cidr

    run = secrets.token_hex(4)
    tag, name = f"ccrp-test/jazzy:{run}", f"ccrp-test-ros2-{run}"
    containers, network = [], None
    try:
        images.build_clone_image(client, tag, CAPTURE_LAYER.format(image=clone_images(DISTRO)), LABELS)
        ipam = docker.types.IPAMConfig(pool_configs=[docker.types.IPAMPool(subnet=free_cidr("10.72.0.0/13"))])
        network = client.networks.create(name, driver="bridge", ipam=ipam, labels=LABELS)
        for side in ("a", "b"):
            containers.append(client.containers.run(tag, ["sleep", "infinity"], name=f"{name}-{side}", network=name,
                                                    labels=LABELS, detach=True))
        for c in containers:
            c.reload()
        yield [(c, c.attrs["NetworkSettings"]["Networks"][name]["IPAddress"]) for c in containers]
    finally:
        for c in containers:
            c.remove(force=True)
        if network is not None:
            network.remove()
        try:
            client.images.remove(tag, force=True)
        except docker.errors.ImageNotFound:
            pass


def sh(container, script: str) -> str:
    code, out = container.exec_run(["sh", "-c", script])
    assert code == 0, f"{script}: exit {code}: {out.decode(errors='replace')}"
    return out.decode().strip()


def capture_start(container, case: str) -> None:
    container.exec_run(["tcpdump", "-i", "eth0", "-n", "-U", "-w", f"/tmp/{case}.pcap", "udp"], detach=True)
    sh(container, f"for i in $(seq 50); do [ -s /tmp/{case}.pcap ] && exit 0; sleep 0.1; done; exit 1")


def capture_counts(container, case: str, a: str, b: str) -> dict[str, int]:
    """Stops the capture and counts its packets: all, multicast, RTPS multicast (239.255.0.1), and
    those not between the two containers."""
    sh(container, "pkill -INT -x tcpdump; while pgrep -x tcpdump >/dev/null; do sleep 0.1; done")
    filters = {"all": "", "multicast": "dst net 224.0.0.0/4", "rtps_multicast": "dst host 239.255.0.1",
               "elsewhere": f"not (host {a} and host {b})"}
    return {k: int(sh(container, f"tcpdump -n -r /tmp/{case}.pcap '{f}' 2>/dev/null | wc -l"))
            for k, f in filters.items()}


def pub_sub(pair, case: str, env: dict[str, str], peers: bool, seconds: float, want: int, timeout: float):
    """Publisher in the first container, subscriber in the second, both captured: the subscriber's
    exit code and output, and each side's capture counts."""
    (pub, a), (sub, b) = pair
    for c in (pub, sub):
        capture_start(c, case)
    base = {"ROS_DOMAIN_ID": DOMAIN, **env}
    env_pub = {**base, **({"ROS_STATIC_PEERS": b} if peers else {})}
    env_sub = {**base, **({"ROS_STATIC_PEERS": a} if peers else {})}
    with ThreadPoolExecutor(2) as pool:
        got = pool.submit(sub.exec_run, [PYTHON, "-c", NODE, "sub", str(want), str(timeout)], environment=env_sub)
        sent = pool.submit(pub.exec_run, [PYTHON, "-c", NODE, "pub", str(seconds)], environment=env_pub)
        code, out = got.result()
        pcode, pout = sent.result()
    assert pcode == 0, f"publisher: exit {pcode}: {pout.decode(errors='replace')}"
    result = code, out.decode(errors="replace").strip(), [capture_counts(c, case, a, b) for c in (pub, sub)]
    print(case, env, "peers" if peers else "no peers", pout.decode().strip(), *result)  # the figures, with -s
    return result


def test_a_node_runs_with_the_venv_python_or_with_setup_sh(pair):
    """The venv's python needs no environment (the wheels' bootstrapper re-executes it with
    LD_LIBRARY_PATH); Debian's python3 needs setup.sh, and fails without it."""
    (c, _), _ = pair
    script = ("import rclpy; from std_msgs.msg import String; from sensor_msgs.msg import Image; "
              "from geometry_msgs.msg import Twist; from rclpy.utilities import get_rmw_implementation_identifier as rmw; "
              "rclpy.init(); n = rclpy.create_node('probe'); n.create_publisher(Image, '/camera', 1).publish(Image()); "
              "n.create_publisher(Twist, '/cmd_vel', 1).publish(Twist()); print(rmw())")
    assert sh(c, f'{PYTHON} -c "{script}"').splitlines()[-1] == "rmw_fastrtps_cpp"
    assert sh(c, f'. /opt/ros/{DISTRO}/setup.sh && python3 -c "{script}"').splitlines()[-1] == "rmw_fastrtps_cpp"
    code, out = c.exec_run(["sh", "-c", f'PYTHONPATH=/opt/ros/{DISTRO}/lib/python3.11/site-packages python3 -c "{script}"'])
    assert code != 0 and b"cannot open shared object file" in out, out


def test_static_peers_carry_the_topic_without_multicast(pair):
    code, out, counts = pub_sub(pair, "static", {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, peers=True,
                                seconds=8, want=10, timeout=20)
    assert code == 0, out
    for side in counts:
        assert side["all"] > 0, counts  # the capture saw the discovery and the data...
        assert side["multicast"] == 0 and side["elsewhere"] == 0, counts  # ...and nothing else


def test_localhost_without_peers_reaches_nobody(pair):
    code, out, counts = pub_sub(pair, "alone", {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}, peers=False,
                                seconds=5, want=1, timeout=6)
    assert code == 1 and out.startswith("received 0"), out
    assert [side["all"] for side in counts] == [0, 0], counts


def test_control_default_range_sends_rtps_multicast(pair):
    """Without the settings above, Jazzy's default (SUBNET) announces by multicast: what the
    capture of the first test would have counted."""
    code, out, counts = pub_sub(pair, "default", {}, peers=False, seconds=4, want=1, timeout=10)
    assert code == 0, out
    assert counts[0]["rtps_multicast"] > 0 and counts[1]["rtps_multicast"] > 0, counts
