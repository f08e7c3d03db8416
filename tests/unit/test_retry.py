"""retry.call and retry.across_zones: what is retried, how often, and what gives up."""

from __future__ import annotations

import pytest

from ccrp_cli.errors import CcrpError
from ccrp_cli.retry import Backoff, ErrorClass, across_zones, call


class Throttled(Exception):
    pass


class NoCapacity(Exception):
    pass


def classify(exc: BaseException) -> ErrorClass:
    return {Throttled: ErrorClass.RETRYABLE, NoCapacity: ErrorClass.ZONE}.get(type(exc), ErrorClass.FATAL)


def flaky(failures: list[BaseException]):
    calls = []

    def fn(*args):
        calls.append(args)
        if failures:
            raise failures.pop(0)
        return "ok"

    return fn, calls


def test_retries_throttling_then_succeeds_with_bounded_jittered_delays():
    slept: list[float] = []
    fn, calls = flaky([Throttled(), Throttled(), Throttled()])
    b = Backoff(attempts=5, base=1.0, cap=3.0, sleep=slept.append, rng=lambda: 1.0)
    assert call(fn, "x", classify=classify, what="create", backoff=b) == "ok"
    assert len(calls) == 4
    assert slept == [1.0, 2.0, 3.0]  # capped


def test_fatal_is_not_retried():
    fn, calls = flaky([ValueError("bad request")])
    with pytest.raises(ValueError):
        call(fn, classify=classify, what="create", backoff=Backoff(sleep=lambda s: None))
    assert len(calls) == 1


def test_gives_up_with_one_line_error():
    fn, calls = flaky([Throttled()] * 10)
    with pytest.raises(CcrpError, match="still failing after 3 attempts"):
        call(fn, classify=classify, what="create", backoff=Backoff(attempts=3, sleep=lambda s: None))
    assert len(calls) == 3


def test_zone_fallback_moves_on_only_for_zone_errors():
    seen = []

    def in_zone(zone):
        seen.append(zone)
        if zone == "a":
            raise NoCapacity("a full")
        return zone

    assert across_zones(["a", "b", "c"], in_zone, classify=classify, what="run") == "b"
    assert seen == ["a", "b"]
    with pytest.raises(ValueError):
        across_zones(["a"], lambda z: (_ for _ in ()).throw(ValueError("quota")), classify=classify, what="run")
    with pytest.raises(CcrpError, match="no capacity in zones a"):
        across_zones(["a"], in_zone, classify=classify, what="run")
