"""bench/relay.py's comparison of a ROS 2 distro with Noetic in one run (issue 28: Jazzy within 2x)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench" / "relay.py"


def load():
    spec = importlib.util.spec_from_file_location("relay_bench", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def figures(p95_median, p95_worst, p50, p95, p50_median=3.0):
    return {"p95_ms_median": p95_median, "p95_ms_worst": p95_worst, "p50_ms_median": p50_median,
            "latency": {"direct": {"p50_ms": 0.5, "p95_ms": 0.7}, "relay": {"p50_ms": p50, "p95_ms": p95}}}


def test_ratios_are_the_distros_figures_over_noetics():
    bench = load()
    jazzy, noetic = figures(6.0, 9.0, 1.5, 3.0, 5.0), figures(2.0, 4.5, 1.0, 1.2, 2.5)
    assert bench.ratios(jazzy, noetic) == {"images_p95_median": 3.0, "images_p95_worst": 2.0, "images_p50_median": 2.0,
                                           "small_relay_p50": 1.5, "small_relay_p95": 2.5}
    # A stream with nothing received has no figure: no ratio rather than a division by zero.
    assert bench.ratios(figures(None, 9.0, 1.5, 3.0), figures(2.0, 0, 1.0, 1.2))["images_p95_median"] is None
    assert bench.ratios(jazzy, figures(2.0, 0, 1.0, 1.2))["images_p95_worst"] is None


SNMP = """Ip: Forwarding DefaultTTL
Ip: 1 64
Udp: InDatagrams NoPorts InErrors OutDatagrams RcvbufErrors SndbufErrors InCsumErrors IgnoredMulti MemErrors
Udp: 5120 3 12 4800 11 0 0 0 0
UdpLite: InDatagrams NoPorts InErrors OutDatagrams RcvbufErrors SndbufErrors InCsumErrors IgnoredMulti MemErrors
UdpLite: 0 0 0 0 0 0 0 0 0
relay 250 130
"""


def test_a_clones_counters_are_its_udp_drops_and_the_relays_cpu_time():
    bench = load()
    figures = bench.parse_counters(SNMP, 100)
    assert figures == {"udp_in": 5120, "udp_rcvbuf_errors": 11, "udp_in_errors": 12, "relay_cpu_s": 3.8}
    # No relay process (its unit not running): no CPU figure rather than a wrong one.
    assert bench.parse_counters(SNMP.replace("relay 250 130", "relay"), 100)["relay_cpu_s"] is None
    after = {**figures, "udp_rcvbuf_errors": 15, "relay_cpu_s": 5.05, "clone_cpu_s": 9.0}
    delta = bench.counters_delta({**figures, "clone_cpu_s": 2.5}, after)
    assert delta == {"udp_in": 0, "udp_rcvbuf_errors": 4, "udp_in_errors": 0, "relay_cpu_s": 1.25, "clone_cpu_s": 6.5}


def test_the_last_hops_writer_profiles_are_the_agents_without_and_with_its_changes(monkeypatch):
    import sys
    import xml.etree.ElementTree as ET

    agent = BENCH.parents[1] / "ccrp_cli" / "agent"
    for name in ("relay", "relay_ros2"):  # relay_ros2 imports relay, as beside it on a clone
        spec = importlib.util.spec_from_file_location(name, agent / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        monkeypatch.setitem(sys.modules, name, module)
        spec.loader.exec_module(module)
    relay_ros2 = sys.modules["relay_ros2"]
    bench = load()
    ns = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}
    profile = relay_ros2.fastdds_profile("")
    profiles = {k: ET.fromstring(v) for k, v in bench.last_hop_profiles(profile).items()}
    assert profiles["agent"].find("f:data_writer/f:times/f:nackResponseDelay", ns) is not None
    # Before: the same participant, Fast DDS's writer defaults.
    before = profiles["agent_writer_defaults"]
    assert before.find("f:data_writer", ns) is None and before.find("f:participant", ns) is not None
    paced = profiles["agent_paced"]
    assert paced.find(".//f:flow_controller_descriptor/f:max_bytes_per_period", ns).text == "65536"
    mode = paced.find("f:data_writer/f:qos/f:publishMode", ns)
    assert (mode.find("f:kind", ns).text, mode.find("f:flow_controller_name", ns).text) == ("ASYNCHRONOUS", "ccrp_paced")


def test_the_ros2_probe_spins_an_executor_or_spin_once_and_both_are_python():
    bench = load()
    # Both ways of taking samples are in the script run in the clones (its spec's "spin" picks one).
    compile(bench.PROBE2, "probe2", "exec")
    assert 'spec.get("spin", "spin_once") == "spin_once"' in bench.PROBE2 and "SingleThreadedExecutor()" in bench.PROBE2
    # The executor is shut down before rclpy, or the spinning thread never ends.
    end = bench.PROBE2[bench.PROBE2.index("stop.set()"):]
    assert end.index("executor.shutdown()") < end.index("rclpy.shutdown()")
