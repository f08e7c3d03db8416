"""What the processes of one test run (pytest-xdist workers) share on this machine and build once
(images): one build at a time, the others wait and then find it there."""

from __future__ import annotations

import fcntl
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def host_lock(name: str) -> Iterator[None]:
    with open(f"/tmp/ccrp-test-{name}.lock", "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        yield
