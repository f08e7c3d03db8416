"""What the dashboard shows and how it reaches the page: the fleet's status polled in a thread,
alerts derived from it and from the fleet's PKI, and a broker that pushes both (and the progress
of actions) to every open page as server-sent events.

Nothing here holds a secret: a row carries only the fields in ROW_FIELDS (what `ccrp status`
prints), alerts are sentences made from those, and PKI alerts read only the index's CNs and dates.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import threading
import time
from collections.abc import Callable
from typing import Any

from ..errors import one_line
from ..models.status import StatusRow
from ..alerts import ERROR_DAYS, WARN_DAYS, _alert, pki_alerts, row_alerts  # noqa: F401 - the page's alerts

# Characters of a failure's line (errors.one_line) the page shows.
SHOWN = 300

# The fields of a `fleet_status` row the page gets (a whitelist: a field added to `ccrp status`
# later reaches the page only when it is added here).
ROW_FIELDS = (
    "robot", "clone", "phase", "status", "state", "public_ip", "vpn_endpoint", "common_ip", "vpn_subnet", "vpn_connected",
    "secrets", "robot_address", "robot_rtt_ms", "master_reachable", "robot_nodes", "stale_nodes", "relay_running",
    "relay_peers", "revoked_at", "autostop_idle_s", "stopped_idle", "watchdog", "power", "nodes",
)


def public_row(row: StatusRow) -> dict:
    # `unreachable` is the error of the failed health check: the page gets only whether it failed.
    return row.model_dump(mode="json", include=set(ROW_FIELDS)) | {"unreachable": bool(row.unreachable)}


class Broker:
    """Fan-out of events to the open pages. Publishers are threads; each subscriber is an
    asyncio queue on the server's loop. The last event of each kind in STICKY is kept and sent
    first to a new subscriber, so a page shows the fleet at once."""

    STICKY = ("fleet",)
    QUEUE_SIZE = 256

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._subscribers: set[asyncio.Queue] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._last: dict[str, str] = {}
        self.closed = False

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    def publish(self, event: str, data: Any) -> None:
        text = json.dumps(data, default=str, separators=(",", ":"))
        with self._lock:
            if event in self.STICKY:
                self._last[event] = text
            subscribers, loop = list(self._subscribers), self._loop
        if loop is None or loop.is_closed():
            return
        for queue in subscribers:
            loop.call_soon_threadsafe(self._offer, queue, (event, text))

    @staticmethod
    def _offer(queue: asyncio.Queue, item) -> None:
        if queue.full():  # a page that stopped reading: drop its oldest event, never block the server
            queue.get_nowait()
        queue.put_nowait(item)

    def last(self, event: str) -> str | None:
        with self._lock:
            return self._last.get(event)

    def subscribe(self) -> asyncio.Queue:
        queue: asyncio.Queue = asyncio.Queue(self.QUEUE_SIZE)
        with self._lock:
            self._subscribers.add(queue)
            for item in self._last.items():
                queue.put_nowait(item)
        return queue

    def unsubscribe(self, queue: asyncio.Queue) -> None:
        with self._lock:
            self._subscribers.discard(queue)

    def close(self) -> None:
        """Every stream ends (server shutdown)."""
        self.closed = True
        with self._lock:
            subscribers, loop = list(self._subscribers), self._loop
        if loop is not None and not loop.is_closed():
            for queue in subscribers:
                loop.call_soon_threadsafe(self._offer, queue, None)


def sse(event: str, text: str) -> str:
    """One server-sent event; `text` is one line of JSON."""
    return f"event: {event}\ndata: {text}\n\n"


class Monitor(threading.Thread):
    """Polls `read()` (the fleet's status rows) every `interval` seconds and publishes the fleet
    event: rows, alerts and when it was read. A failed read becomes an alert, not a dead thread."""

    def __init__(self, broker: Broker, read: Callable[[], list[StatusRow]], pki_check: Callable[[list[str]], list[dict]],
                 interval: float, fleet_name: str, provider_kind: str, ros2: bool = False) -> None:
        super().__init__(name="ccrp-dashboard-monitor", daemon=True)
        self.broker, self.read, self.pki_check = broker, read, pki_check
        self.interval, self.fleet_name, self.provider_kind, self.ros2 = interval, fleet_name, provider_kind, ros2
        self.stopping = threading.Event()
        self.wake = threading.Event()
        self.reads = 0

    def snapshot(self) -> dict:
        t0 = time.monotonic()
        alerts: list[dict] = []
        try:
            read = self.read()
        except Exception as exc:  # noqa: BLE001 - shown on the page; the next poll tries again
            read = None
            alerts.append(_alert("error", "status-failed", None, f"reading the fleet's status failed: {one_line(exc, SHOWN)}"))
        for row in read or []:
            alerts.extend(row_alerts(row))
        rows = [public_row(r) for r in read] if read is not None else None
        try:
            alerts.extend(self.pki_check([r.robot for r in read or []]))
        except Exception as exc:  # noqa: BLE001
            alerts.append(_alert("error", "pki-failed", None, f"reading the fleet's PKI failed: {one_line(exc, SHOWN)}"))
        self.reads += 1
        return {
            "fleet": self.fleet_name, "provider": self.provider_kind, "ros2": self.ros2, "rows": rows, "alerts": alerts,
            "read_at": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
            "read_seconds": round(time.monotonic() - t0, 2), "interval": self.interval,
        }

    def run(self) -> None:
        while not self.stopping.is_set():
            self.broker.publish("fleet", self.snapshot())
            self.wake.wait(self.interval)
            self.wake.clear()

    def refresh(self) -> None:
        """Read again now (after an action)."""
        self.wake.set()

    def stop(self) -> None:
        self.stopping.set()
        self.wake.set()
