"""The one place for retries: bounded exponential backoff with full jitter, and zone fallback.

Providers classify their SDK's exceptions (`classify(exc) -> ErrorClass`); this module decides
what to do with each class. Nothing else in ccrp sleeps-and-retries an API call, and every
wait-until-ready loop (a clone serving, host keys on a console, a robot connected) is `poll`.
"""

from __future__ import annotations

import random
import time
from enum import Enum
from typing import Callable, Iterable, TypeVar

from .errors import CcrpError

T = TypeVar("T")


class ErrorClass(str, Enum):
    RETRYABLE = "retryable"  # throttling, 5xx, connection reset: same call again later
    ZONE = "zone"  # capacity / zone unavailable: the next zone may work
    REGION = "region"  # quota / region-wide: no zone in this region will work
    FATAL = "fatal"  # bad request, auth, not found: retrying cannot help


Classifier = Callable[[BaseException], ErrorClass]


class Backoff:
    """Delays for attempt 1, 2, ...: uniform(0, min(cap, base * 2**n)) (AWS's "full jitter")."""

    def __init__(self, attempts: int = 8, base: float = 0.25, cap: float = 10.0,
                 sleep: Callable[[float], None] = time.sleep, rng: Callable[[], float] = random.random) -> None:
        self.attempts, self.base, self.cap, self.sleep, self.rng = attempts, base, cap, sleep, rng

    def delay(self, n: int) -> float:
        return self.rng() * min(self.cap, self.base * (2 ** n))


DEFAULT = Backoff()


def call(fn: Callable[..., T], *args, classify: Classifier, what: str, backoff: Backoff = DEFAULT,
         on_retry: Callable[[str], None] | None = None, **kwargs) -> T:
    """fn(*args, **kwargs), retried while `classify` says RETRYABLE, at most backoff.attempts times.
    Non-retryable errors propagate unchanged so callers (zone fallback, rollback) can see them."""
    for n in range(backoff.attempts):
        try:
            return fn(*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - classified below
            if classify(exc) is not ErrorClass.RETRYABLE:
                raise
            if n == backoff.attempts - 1:
                raise CcrpError(
                    f"{what}: still failing after {backoff.attempts} attempts ({type(exc).__name__}: {str(exc)[:160]})",
                    hint="the cloud is throttling or unavailable; try again later",
                ) from exc
            if on_retry:
                on_retry(f"{what}: {type(exc).__name__}, retry {n + 1}/{backoff.attempts - 1}")
            backoff.sleep(backoff.delay(n))
    raise AssertionError("unreachable")


def across_zones(zones: Iterable[str], fn: Callable[[str], T], *, classify: Classifier, what: str,
                 exhausted: Callable[[str, list[str], BaseException], CcrpError | None] = lambda *_: None) -> T:
    """fn(zone) for each zone in order until one works; only ZONE-class failures move on. When every
    zone failed, `exhausted(what, tried, last)` may name the cause better than "no capacity"."""
    tried: list[str] = []
    last: BaseException | None = None
    for zone in zones:
        try:
            return fn(zone)
        except Exception as exc:  # noqa: BLE001
            if classify(exc) is not ErrorClass.ZONE:
                raise
            tried.append(zone)
            last = exc
    if last is not None and (err := exhausted(what, tried, last)) is not None:
        raise err from last
    raise CcrpError(
        f"{what}: no capacity in zones {', '.join(tried) or '(none listed)'} ({str(last)[:160]})",
        hint="add zones to the inventory's provider.zones or pick another instance type",
    ) from last


class PollTimeout(Exception):
    """poll() ran out of time; `last` is the probe's last answer, for the caller's message."""

    def __init__(self, last: object, seconds: float) -> None:
        super().__init__(f"not done after {seconds:.0f} s")
        self.last, self.seconds = last, seconds


def poll(probe: Callable[[], tuple[bool, T]], *, timeout: float, interval: float,
         progress: Callable[[float], None] | None = None, every: float = 60.0, sleep=time.sleep) -> T:
    """probe() every `interval` s until it says done; returns its answer. After `timeout` s it
    raises PollTimeout with the last answer; `progress(elapsed)` is called every `every` s."""
    t0 = time.monotonic()
    noted = t0
    while True:
        done, last = probe()
        if done:
            return last
        now = time.monotonic()
        if now - t0 >= timeout:
            raise PollTimeout(last, now - t0)
        if progress and now - noted >= every:
            progress(now - t0)
            noted = now
        sleep(interval)
