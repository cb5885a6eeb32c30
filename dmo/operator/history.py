"""The traffic of the DMO's day, kept so that a process that joins late learns what it missed: every payload the
DMO put on the wire and every one it received, in order, with its time (docs/recording.md, "Late joiners").

Zenoh delivers a message to the subscribers present when it is sent, and to nobody else. A recorder started after
the agents registered would miss their registrations, and the recording could not be re-settled. The DMO sees
the whole day (it is the one every agent talks to), so it answers queries on its run's keys: the latest message
on each of its keys, or, with the parameter ``history``, the whole traffic. This works for any Zenoh client, with
or without ``zenoh.ext``; a DMO resumed from its journal answers with the traffic it journaled.
"""

from __future__ import annotations

import bisect
import json
import os
import re
import tempfile
import threading
from array import array
from collections.abc import Iterable, Iterator

import zenoh

from messages.keys import HISTORY, ROOT, SINCE, parse_key
from messages.transport.bus import Entry

from .journal import Journal, line_of, traffic, traffic_entry


class DayHistory:
    """Every payload the DMO sent or received, as (key, payload, ns); thread-safe (Zenoh's threads record).

    The traffic is kept on disk, not in memory, so that the DMO does not grow with the days of a run: in the
    journal when the DMO keeps one (which also brings back the traffic of a DMO restarted on it), else in a
    temporary file of the same lines that goes with the process. Memory holds only the latest message the DMO
    published on each of its keys, which is bounded by the agents, not the days, and a mark every ``MARK_EVERY``
    lines of traffic (where it starts in the file, and the latest time before it) so that a question about the
    traffic since some time reads the file from there, not from the run's start (16 bytes per mark)."""

    def __init__(self, journal: Journal | None = None):
        self._journal = journal
        self._scratch = None if journal else tempfile.TemporaryFile()  # noqa: SIM115
        self._size = 0  # the scratch file's
        self._latest: dict[str, Entry] = {}
        self._lock = threading.Lock()
        self._mark_at, self._mark_ns = array("q"), array("q")  # where each mark is, and the latest ns before it
        self._recorded = 0
        self._answered = threading.Condition(self._lock)
        self._covered = 0  # lines of traffic that a history answer read to its end has covered
        self._latest_ns = -1
        for entry in traffic(journal.entries if journal else ()):
            self._keep_latest(entry)
            self._latest_ns = max(self._latest_ns, entry[2])

    def record(self, key: str, payload: bytes, at: int) -> None:
        entry = (key, bytes(payload), at)
        with self._lock:
            self._keep_latest(entry)
            if self._journal is not None:
                offset = self._journal.traffic(*entry)
            else:
                line = line_of(traffic_entry(*entry))
                offset = self._size
                self._scratch.write(line)
                self._scratch.flush()
                self._size += len(line)
            if self._recorded % MARK_EVERY == 0:
                self._mark_at.append(offset)
                self._mark_ns.append(self._latest_ns)  # never decreasing: a running maximum
            self._recorded += 1
            self._latest_ns = max(self._latest_ns, at)

    def _keep_latest(self, entry: Entry) -> None:
        if _published_by_dmo(entry[0]):
            self._latest[entry[0]] = entry

    def answer(self, key_expr: str, parameters: str) -> Iterable[Entry]:
        """The replies to a query: with ``history`` among the parameters every entry on a matching key, in order,
        and with ``since=NS`` too only those seen at or after NS, read from the file as they are replied (a day's
        traffic is never all in memory at once); otherwise the latest message the DMO published on each matching
        key. A ``since`` that is not a whole number of nanoseconds is a ValueError (an error reply)."""
        asked, matches = zenoh.KeyExpr(key_expr), {}
        given = _parameters(parameters)

        def matching(key: str) -> bool:
            if key not in matches:
                matches[key] = asked.intersects(zenoh.KeyExpr(key))
            return matches[key]

        if HISTORY in given:
            if not _whole_run(key_expr):
                raise ValueError(f"{HISTORY} is answered for the whole run only ({ROOT}/<run>/**), "
                                 f"not {key_expr[:200]}")
            since = _nanoseconds(given.get(SINCE, "0"))
            return (e for e in traffic(map(json.loads, self._lines_since(since))) if e[2] >= since and matching(e[0]))
        with self._lock:
            if not _WILD.search(key_expr):  # one key (an agent asking for the clock or its award): no scan
                return [self._latest[key_expr]] if key_expr in self._latest else []
            latest = list(self._latest.values())
        return sorted((e for e in latest if matching(e[0])), key=lambda e: e[2])

    def _lines_since(self, since: int) -> Iterator[bytes]:
        """The file's lines from the last mark before which all traffic is older than ``since`` (from the start if
        none) to the last line recorded, read a chunk at a time and without holding up ``record``."""
        with self._lock:
            before = bisect.bisect_left(self._mark_ns, since)  # marks before which everything is older than since
            start = self._mark_at[before - 1] if before else 0
            end = self._journal.size if self._journal is not None else self._size
            recorded = self._recorded
        if self._journal is None:
            yield from _lines(self._scratch.fileno(), start, end)
        else:
            fd = os.open(self._journal.path, os.O_RDONLY)
            try:
                yield from _lines(fd, start, end)
            finally:
                os.close(fd)
        with self._answered:  # read to its end: whoever asked has had all the traffic recorded when it asked
            self._covered = max(self._covered, recorded)
            self._answered.notify_all()

    def wait_answered(self, timeout_s: float) -> bool:
        """Wait until a question about the traffic has been answered to the end of all the traffic recorded (at
        most ``timeout_s``); whether it has been. The recorder asks whenever an agent leaves, so a DMO that waits
        for this before it leaves knows that the recording lacks nothing that the network lost on its way."""
        with self._answered:
            return self._answered.wait_for(lambda: self._covered >= self._recorded, timeout_s)


def _lines(fd: int, start: int, end: int, chunk: int = 1 << 16) -> Iterator[bytes]:
    """The lines of an open file between two offsets of line starts, read ``chunk`` bytes at a time with
    ``os.pread`` (which leaves the file's position, where its writer appends, alone)."""
    rest = b""
    while start < end:
        data = os.pread(fd, min(chunk, end - start), start)
        if not data:
            break
        start += len(data)
        *lines, rest = (rest + data).split(b"\n")
        yield from lines


MARK_EVERY = 1000  # lines of traffic between two marks: a day of 100 agents is about 9,000


# What makes a key expression match more than itself (Zenoh's wildcards and its $* sub-chunk wildcard). Asked for
# one key, the DMO answers from its latest at once: a thousand agents asking for the clock while it scanned its
# thousands of keys (awards, statements, receipts) for each of them had it answer too late, and asking again made
# it later still.
_WILD = re.compile(r"[*$]")


def asks_history(key_expr: str, parameters: str) -> bool:
    """Whether a query asks for the traffic of the whole run, not the latest: an answer that takes long
    (``Bus.serve``'s ``slow``). One for less than the whole run is refused at once (``answer``): only a reader,
    whom the router's access control lets ask for the whole run, gets the traffic."""
    return HISTORY in _parameters(parameters) and _whole_run(key_expr)


def _whole_run(key_expr: str) -> bool:
    parts = key_expr.split("/")
    return len(parts) == 3 and parts[0] == ROOT and parts[2] == "**"


def _parameters(parameters: str) -> dict[str, str]:
    return dict(p.split("=", 1) if "=" in p else (p, "") for p in parameters.split(";") if p)


def _nanoseconds(text: str) -> int:
    if not text.isdigit():
        raise ValueError(f"{SINCE}={text!r}: not a time in whole nanoseconds since the Unix epoch")
    return int(text)


def _published_by_dmo(key: str) -> bool:
    try:
        return parse_key(key).role == "dmo"
    except ValueError:
        return False
