"""The recorder's loop: every payload under one run prefix, as it arrived, valid or not, into a RecordingWriter;
for a recorder that joins late, what the run said before it joined, asked of the DMO (``backfill``); and what the
network lost on the way to it, asked of the DMO as the day goes on (``catch up``)."""

from __future__ import annotations

import collections
import hashlib
import logging
import queue
import threading
import time
from typing import Callable

from ..keys import HISTORY, parse_key
from ..schemas import DMO
from ..transport.heap import return_free_memory
from .writer import RecordingWriter

log = logging.getLogger("dmosim.recorder")
CATCH_UP_KINDS = ("clock", "day_summary")  # a DMO message of these kinds: time to ask it for what this recorder lacks
IN_FLIGHT_S = 2.0  # what the DMO sent this recently may still be on its way: not yet taken as lost
# Payloads of the DMO's remembered per key: catching up asks for the latest on each key, which is the last one that
# came on it, or one still missing; a few more cover those a delay fault made come out of order.
SEEN_PER_KEY = 8


class LatestSeen:
    """The last ``SEEN_PER_KEY`` payloads of the DMO's queued on each of its keys (their digests): what catching up
    compares the DMO's answers with. Bounded by the keys, however long the run."""

    def __init__(self):
        self._by_key: dict[str, collections.deque[bytes]] = {}

    def add(self, key: str, payload: bytes) -> None:
        self._by_key.setdefault(key, collections.deque(maxlen=SEEN_PER_KEY)).append(_digest(payload))

    def __contains__(self, item: tuple[str, bytes]) -> bool:
        key, payload = item
        return _digest(payload) in self._by_key.get(key, ())

    def __len__(self) -> int:
        """Payloads remembered."""
        return sum(len(digests) for digests in self._by_key.values())


class Recorder:
    """Records every payload under one run prefix, as it arrived, valid or not: Zenoh's threads only enqueue,
    and ``run`` writes on the calling thread until ``stop`` is set, then drains the queue, closes the file and only
    then undeclares (what arrives after the stop is not recorded).

    The liveliness token ``alive/<name>`` (``alive/recorder`` for ``dmosim record``) is declared after the
    subscription and the backfill, so whoever sees the recorder present (the DMO waits for it) knows that it is
    already listening.
    """

    def __init__(self, bus, writer: RecordingWriter, announce: bool = True):
        self.bus, self.writer, self.announce = bus, writer, announce
        # A Queue, not a SimpleQueue: CPython 3.11's SimpleQueue.get(timeout) blocks for good when a signal handler
        # (SIGTERM's, which stops the recorder) runs past the wait's deadline, as it may on a loaded machine
        self._queue: queue.Queue = queue.Queue()
        self._subscription = None
        self._token = None
        self._live: collections.Counter | None = None  # (key, payload) received live while backfilling
        self._live_lock = threading.Lock()
        self.backfilled = 0
        self.caught_up = 0  # payloads the network lost on the way here, asked of the DMO afterwards
        self.seen = LatestSeen()  # the DMO's payloads queued, the latest of each key
        self._summary = bus.keys.summary()  # once a day's summary is written, the memory the day used goes back
        self._wake = threading.Event()
        self._catching_up: threading.Thread | None = None
        self.first_received_ns = 0   # receipt of the first message, and the end of the last write: the span the
        self.last_written_ns = 0     # recorder kept up with (its sustained rate is messages / span)

    def start(self, backfill: bool = True, timeout_s: float = 10.0) -> int:
        """Subscribe to the whole run; then, with ``backfill``, ask the DMO for the run's traffic so far and queue
        what the subscription did not get (``backfilled``, which this returns). Each backfilled payload keeps the
        time the DMO saw it as its log time."""
        self._live = collections.Counter() if backfill else None
        self._subscription = self.bus.subscribe_raw(self.bus.keys.everything(), self._received)
        if backfill:
            self.backfilled = self._backfill(timeout_s)
            self._catching_up = threading.Thread(target=self._catch_up_loop, name="recorder-catch-up", daemon=True)
            self._catching_up.start()
        if self.announce:
            self._token = self.bus.session.liveliness().declare_token(self.bus.keys.alive(self.bus.name))
        return self.backfilled

    def _received(self, key: str, payload: bytes, at: int) -> None:
        parsed = _parsed(key)
        with self._live_lock:
            if self._live is not None:
                self._live[key, payload] += 1
            self._saw(parsed, key, payload)
        self._queue.put((key, payload, at, True))
        if self._catching_up is not None and parsed is not None and parsed.kind in CATCH_UP_KINDS:
            self._wake.set()

    def _saw(self, parsed, key: str, payload: bytes) -> None:
        """Note a payload of the DMO's (what catching up asks it for) as queued; the caller holds the lock."""
        if parsed is not None and parsed.role == DMO:
            self.seen.add(key, payload)

    def _catch_up_loop(self) -> None:
        """On each clock and day summary of the DMO's, ask it for the latest message on each of its keys and queue
        those that never arrived here (Zenoh delivers once; a message the network lost would be missing from the
        recording, though its agent asked the DMO for it again). Off Zenoh's threads: a query must not block one."""
        while self._subscription is not None:
            if not self._wake.wait(timeout=0.5):
                continue
            self._wake.clear()
            try:
                self.caught_up += self._catch_up()
            except Exception:  # the DMO may be gone: what is missing stays missing, the recording goes on
                log.debug("catching up failed", exc_info=True)
            return_free_memory()  # the answer, the latest on every key of the DMO's (awards, statements), is gone

    def _catch_up(self) -> int:
        added, now = 0, time.time_ns()
        for key, payload, at in self.bus.fetch(self.bus.keys.everything(), timeout_s=5.0):
            with self._live_lock:
                missing = at is not None and now - at > IN_FLIGHT_S * 1e9 and (key, payload) not in self.seen
                if missing:
                    self.seen.add(key, payload)
            if missing:
                self._queue.put((key, payload, at, False))
                added += 1
        if added:
            log.info("caught up on %d message(s) the network lost on the way here", added)
        return added

    def _backfill(self, timeout_s: float) -> int:
        """The DMO's history of the run (dmo/operator/history.py) minus what arrived live meanwhile: a payload the
        subscription already delivered is in both, once for each time it arrived."""
        entries = self.bus.fetch(f"{self.bus.keys.everything()}?{HISTORY}", timeout_s)
        with self._live_lock:
            live, self._live = self._live, None
        added = 0
        for key, payload, at in entries:
            if live[key, payload] > 0:
                live[key, payload] -= 1
                continue
            with self._live_lock:
                self._saw(_parsed(key), key, payload)
            self._queue.put((key, payload, at or time.time_ns(), False))
            added += 1
        if added:
            log.info("backfilled %d messages from the DMO's history of run %s", added, self.bus.keys.run_id)
        return added

    def run(self, stop: threading.Event, on_write: Callable[[str, bool], None] | None = None) -> None:
        writer, q = self.writer, self._queue
        try:
            while not stop.is_set():
                try:
                    item = q.get(timeout=min(0.1, writer.flush_interval_s))
                except queue.Empty:
                    writer.tick()
                    continue
                self._write(*item, on_write)
                for _ in range(writer.chunk_messages):  # drain a burst before looking at the clock again
                    try:
                        item = q.get_nowait()
                    except queue.Empty:
                        break
                    self._write(*item, on_write)
                writer.tick()
        finally:  # the file first: nothing of Zenoh's (undeclaring, closing) stands between the run and its footer
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                self._write(*item, on_write)
            writer.close()
            self.stop()

    def _write(self, key: str, payload: bytes, at: int, live: bool, on_write) -> None:
        valid = self.writer.write(key, payload, at)
        if key == self._summary:
            return_free_memory()
        if live:  # a backfilled payload's time is the DMO's, long before this recorder's work
            self.first_received_ns = self.first_received_ns or at
        self.last_written_ns = time.time_ns()
        if on_write is not None:
            on_write(key, valid)

    @property
    def busy_s(self) -> float:
        return max(0.0, (self.last_written_ns - self.first_received_ns) / 1e9)

    def stop(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            try:
                token.undeclare()
            except Exception:  # the session may be closing already
                log.debug("could not undeclare the recorder's token", exc_info=True)
        subscription, self._subscription = self._subscription, None
        if subscription is not None:
            subscription.close()


def _digest(payload: bytes) -> bytes:
    return hashlib.sha256(payload).digest()


def _parsed(key: str):
    try:
        return parse_key(key)
    except ValueError:  # a key outside the layout: recorded, never caught up
        return None
