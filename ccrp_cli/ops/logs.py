"""ccrp logs across the fleet (docs/workloads.md, Logs): the journals of the selected robots' nodes
(or of one of ccrp's units) on their clones, merged by the journal's time, each line labelled
robot/node; with --follow one reader per clone, each from its own journal cursor."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from ..errors import CcrpError, InputError, one_line
from ..services.workloads import UNIT_PREFIX, log_units, read_journal

if TYPE_CHECKING:
    from ..fleet import Fleet
    from ..models.state import FleetState
    from ..providers.base import Reaches

POLL_SECONDS = 1.0
FOLLOW_PAGE = 500  # lines a poll reads at most (it reads on at once after a full page)
POLLERS = 8  # clones read at once while following (each read is one exec)


def select(fleet: Fleet, state: FleetState, robots: str | None, type_: str | None, every: bool) -> list[str]:
    """The robots --robot R[,R...], --type T or --all name (exactly one of them); an unknown robot or
    type is an InputError (exit 2) before anything is read."""
    from .deploy import targets

    if sum((robots is not None, type_ is not None, every)) != 1:
        raise InputError("name the robots to read: --robot R[,R...], --type T or --all")
    if robots is not None:
        names = [n.strip() for n in robots.split(",") if n.strip()]
        if not names:
            raise InputError("--robot names no robot")
        return [fleet.robot(state, n).name for n in dict.fromkeys(names)]
    return targets(fleet, state, None, type_)


@dataclass
class Reader:
    """One clone's journal: the units read on it and the cursor to read on from."""

    robot: str
    units: list[str]
    cursor: str | None = None
    read: bool = False  # its first read done (a clone down at first is read as at first when it answers)
    printed: set[str] = field(default_factory=set)  # cursors the first read showed, for the first poll
    down: bool = False  # reported unreadable once; asked again each round, quietly


def readers(fleet: Fleet, state: FleetState, robots: list[str], name: str | None) -> list[Reader]:
    """A reader per robot that has the node (or any node, without NAME). With several robots, those
    without it are left out; none having it is the error of the first (exit 2)."""
    out, refused = [], []
    for robot in robots:
        try:
            out.append(Reader(robot, log_units(fleet.inventory, fleet.robot(state, robot), name)))
        except InputError as exc:
            refused.append(exc)
    if not out:
        raise refused[0]
    return out


def node_of(unit: str) -> str:
    """The name `ccrp logs` takes for a unit: mapper for ccrp-run-mapper.service, relay for ccrp-relay.service."""
    base = unit.removesuffix(".service")
    for prefix in (UNIT_PREFIX, "ccrp-"):
        if base.startswith(prefix):
            return base[len(prefix):]
    return base


def record(robot: str, entry: dict) -> dict:
    """A journal entry as `ccrp logs` shows it: {robot, node, time (ISO 8601, UTC), message}."""
    return {"robot": robot, "node": node_of(entry["unit"]), "time": entry["time"], "message": entry["message"]}


def merge(batches: list[list[dict]]) -> list[dict]:
    """Records of several clones and nodes in one list ordered by time. The sort is stable, so a tie
    keeps the order of the batches (as the robots were named) and each node's journal order."""
    return sorted((r for batch in batches for r in batch), key=lambda r: r["time"])


def first_read(provider: Reaches, reader: Reader, lines: int, since_s: int | None, follow: bool) -> list[dict]:
    """The last `lines` of each of the reader's units (within --since), as records. Following, the
    journal's tail cursor is taken first, whatever --since matches: the polls read on from it, so a
    first read that found nothing never makes them print the history; a line both reads see is
    shown once."""
    if follow:
        _, reader.cursor = read_journal(provider, reader.robot, reader.units, 1)
    entries = []
    for unit in reader.units:  # one read per unit: `lines` of each, however much another logs
        got, _ = read_journal(provider, reader.robot, [unit], lines, since_s)
        entries += got
    reader.read = True
    reader.printed = {e["cursor"] for e in entries if e.get("cursor")}
    return merge([[record(reader.robot, e) for e in entries]])


def poll(provider: Reaches, reader: Reader) -> tuple[list[dict], bool]:
    """The entries after the reader's cursor (one bounded page), and whether the page was full."""
    entries, reader.cursor = read_journal(provider, reader.robot, reader.units, FOLLOW_PAGE, cursor=reader.cursor)
    full = len(entries) >= FOLLOW_PAGE
    if reader.printed:  # the first poll after the first read: what that read showed already
        entries = [e for e in entries if e.get("cursor") not in reader.printed]
        reader.printed = set()
    return [record(reader.robot, e) for e in entries], full


@dataclass
class Logs:
    """`ccrp logs` on the selected clones: a first read of each, then (following) rounds of polls,
    every clone in parallel in each round."""

    provider: Reaches
    readers: list[Reader]
    lines: int
    since_s: int | None
    following: bool
    warn: Callable[[str], None]

    def _one(self, reader: Reader) -> tuple[list[dict], bool]:
        """One clone's new records; a clone that cannot be read is reported once, the others go on."""
        try:
            if reader.read:
                got = poll(self.provider, reader)
            else:
                got = first_read(self.provider, reader, self.lines, self.since_s, self.following), False
        except (CcrpError, OSError) as exc:  # a stopped or unreachable clone (an engine's or a socket's error)
            if not reader.down:
                reader.down = True
                self.warn(f"cannot read robot {reader.robot!r}'s clone: {one_line(exc, 300)}"
                          + ("; following the others" if self.following else ""))
            return [], False
        if reader.down:
            reader.down = False
            self.warn(f"robot {reader.robot!r}'s clone answers again")
        return got

    def _round(self, pool: ThreadPoolExecutor) -> tuple[list[dict], bool]:
        results = list(pool.map(self._one, self.readers))
        return merge([r for r, _ in results]), any(full for _, full in results)

    def run(self, show: Callable[[list[dict]], None], sleep: Callable[[float], None]) -> int:
        """Show the first read of every clone, merged; following, every round's new lines until
        Ctrl-C (KeyboardInterrupt, the caller's). The exit code: 0, or without --follow 1 when no
        clone could be read and 3 when some could not (as the other fan-out commands)."""
        pool = ThreadPoolExecutor(max_workers=min(POLLERS, len(self.readers)), thread_name_prefix="ccrp-logs")
        try:
            records, full = self._round(pool)
            show(records)
            while self.following:
                if not full:  # after a full page more is waiting: read on at once
                    sleep(POLL_SECONDS)
                records, full = self._round(pool)
                show(records)
        finally:  # Ctrl-C: no wait here for the reads under way
            pool.shutdown(wait=False, cancel_futures=True)
        down = sum(r.down for r in self.readers)
        return 0 if not down else 1 if down == len(self.readers) else 3
