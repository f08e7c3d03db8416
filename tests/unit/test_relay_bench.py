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


def figures(p95_median, p95_worst, p50, p95):
    return {"p95_ms_median": p95_median, "p95_ms_worst": p95_worst,
            "latency": {"direct": {"p50_ms": 0.5, "p95_ms": 0.7}, "relay": {"p50_ms": p50, "p95_ms": p95}}}


def test_ratios_are_the_distros_figures_over_noetics():
    bench = load()
    jazzy, noetic = figures(6.0, 9.0, 1.5, 3.0), figures(2.0, 4.5, 1.0, 1.2)
    assert bench.ratios(jazzy, noetic) == {"images_p95_median": 3.0, "images_p95_worst": 2.0,
                                           "small_relay_p50": 1.5, "small_relay_p95": 2.5}
    # A stream with nothing received has no figure: no ratio rather than a division by zero.
    assert bench.ratios(figures(None, 9.0, 1.5, 3.0), figures(2.0, 0, 1.0, 1.2))["images_p95_median"] is None
    assert bench.ratios(jazzy, figures(2.0, 0, 1.0, 1.2))["images_p95_worst"] is None
