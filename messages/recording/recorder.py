"""The recorder's loop: every payload under one run prefix, as it arrived, valid or not, into a RecordingWriter;
for a recorder that joins late, what the run said before it joined, asked of the DMO (``backfill``); and what the
network lost on the way to it, asked of the DMO on each day summary and whenever an agent leaves (``catch up``):
everything the DMO sent or received since the last. Agents leave at the run's end, once they have their last
statements, so the last check comes after the last day's messages even when every one of them was lost on its
way here (the DMO waits for that check before it leaves: dmo/operator/day.py)."""

from __future__ import annotations

import bisect
import collections
import hashlib
import logging
import queue
import threading
import time
from array import array
from typing import Callable

from ..budget import SenderBudget
from ..keys import HISTORY, SINCE, agent_of, parse_key
from ..schemas import DMO
from ..transport.heap import return_free_memory
from .layout import DROPPED_METADATA
from .writer import RecordingWriter

log = logging.getLogger("dmosim.recorder")
HISTORY_KINDS = ("day_summary",)  # a DMO message of these kinds: time to ask it for its traffic since the last check
IN_FLIGHT_S = 2.0  # what the DMO sent or saw this recently may still be on its way: not yet taken as lost
HISTORY_TIMEOUT_S = 60.0  # a day's traffic of a thousand agents is a few hundred thousand replies
CLOSING_WAIT_S = 15.0  # how long a stopping recorder lets a check under way finish (dmosim run gives it 60 s)


class Seen:
    """Digests of the payloads queued for the file in the current window and the one before it: what catching up
    compares the DMO's answers with. A window ends at each check of the DMO's history, which covers everything
    the DMO saw up to a cutoff; what came before the previous window was checked then. The current window's are
    16-byte digests in a set; the previous window's, looked up less, 8 bytes each in a sorted array, so what a
    day leaves behind for the next is a tenth of what it held (a recorder's memory does not step up after day 1)."""

    def __init__(self):
        self._current: set[bytes] = set()
        self._previous = array("Q")
        self.since = 0  # the DMO's history is checked from this time on (ns): what came before was checked

    def add(self, key: str, payload: bytes) -> None:
        self._current.add(_digest(key, payload))

    def __contains__(self, item: tuple[str, bytes]) -> bool:
        digest = _digest(*item)
        if digest in self._current:
            return True
        short = _short(digest)
        at = bisect.bisect_left(self._previous, short)
        return at < len(self._previous) and self._previous[at] == short

    def checked_until(self, cutoff: int) -> None:
        """The DMO's history before ``cutoff`` (ns) is in the file: start the next window there."""
        self._previous = array("Q", sorted(map(_short, self._current)))
        self._current, self.since = set(), cutoff

    def __len__(self) -> int:
        """Payloads remembered."""
        return len(self._current) + len(self._previous)


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
        self.seen = Seen()  # the payloads queued in the current catch-up window and the one before
        self._summary = bus.keys.summary()  # once a day's summary is written, the memory the day used goes back
        self._clock = bus.keys.clock()  # each clock message starts a new window of the agents' budgets
        self.budget = SenderBudget()  # what each agent may send in a window before the rest is dropped unread
        self.dropped: collections.Counter[str] = collections.Counter()  # sender ("" for a key naming none) -> how many
        self._wake = threading.Event()  # a day summary came, or an agent left: check the DMO's history
        self._dmo_gone = threading.Event()  # the DMO left: a check under way waits for an answer that cannot come
        self._closed = threading.Event()  # set as the recorder closes: a check waiting out IN_FLIGHT_S ends its wait
        self._answered = threading.Event()  # the check under way has the DMO's whole answer: it needs no DMO to end
        self._catching_up: threading.Thread | None = None
        self.first_received_ns = 0   # receipt of the first message, and the end of the last write: the span the
        self.last_written_ns = 0     # recorder kept up with (its sustained rate is messages / span)

    def start(self, backfill: bool = True, timeout_s: float = 10.0) -> int:
        """Subscribe to the whole run; then, with ``backfill``, ask the DMO for the run's traffic so far and queue
        what the subscription did not get (``backfilled``, which this returns). Each backfilled payload keeps the
        time the DMO saw it as its log time."""
        self._live = collections.Counter() if backfill else None
        self.bus.gate = self._admit
        self._subscription = self.bus.subscribe_raw(self.bus.keys.everything(), self._received)
        if backfill:
            self.backfilled = self._backfill(timeout_s)
            self._catching_up = threading.Thread(target=self._catch_up_loop, name="recorder-catch-up", daemon=True)
            self._catching_up.start()
            self.bus.watch_presence(lambda name: None, self._left, history=False)
        if self.announce:
            self._token = self.bus.session.liveliness().declare_token(self.bus.keys.alive(self.bus.name))
        return self.backfilled

    def _admit(self, key: str, size: int) -> bool:
        """The bus's gate: the DMO's messages always; an agent's within its budget of the window (the DMO's phase or
        hour, as its clock messages say), as the DMO keeps it: what one agent sends cannot swell the recorder's
        queue or the file (messages/budget.py)."""
        parsed = _parsed(key)
        return (parsed is not None and parsed.role == DMO) or not self.budget.admit(agent_of(key), size)

    def _next_window(self) -> None:
        """The DMO's clock moved on (or the recording ends): every agent's budget starts afresh, and what the window
        dropped of each is added to ``dropped``."""
        self.dropped.update({a or "": n for a, n in self.budget.next_window().items()})

    def _received(self, key: str, payload: bytes, at: int) -> None:
        if key == self._clock:
            self._next_window()
        parsed = _parsed(key)
        with self._live_lock:
            if self._live is not None:
                self._live[key, payload] += 1
            self.seen.add(key, payload)
        self._queue.put((key, payload, at, True))
        if (self._catching_up is not None and parsed is not None and parsed.role == DMO
                and parsed.kind in HISTORY_KINDS):
            self._wake.set()

    def _left(self, name: str) -> None:
        """A process of the run left: if it is an agent, the DMO may be about to end the run (liveliness is never
        lost as a message may be), so check its history now; if it is the DMO, nobody is left to ask."""
        if name == DMO:
            self._dmo_gone.set()
        else:
            self._wake.set()

    def _catch_up_loop(self) -> None:
        """On each day summary of the DMO's and each agent that leaves, ask the DMO for everything it sent or
        received since the last, and queue what never arrived here. Zenoh delivers once: a message the network lost
        on the way here (an agent's registration behind a router link that went down, an award its agent alone
        asked for again, a statement dropped by a fault) would be missing from the recording. Off Zenoh's threads:
        a query must not block one."""
        while not self._closed.is_set():
            if not self._wake.wait(timeout=0.5) or self._closed.is_set():  # closing wakes it to end, not to check
                continue
            self._wake.clear()
            try:
                self.caught_up += self._check_history()
            except Exception:  # the DMO may be gone: what is missing stays missing, the recording goes on
                log.debug("catching up failed", exc_info=True)
            return_free_memory()  # what the check used is gone

    def _check_history(self) -> int:
        """Everything the DMO sent or received since the last check that never came here: what it saw in the last
        ``IN_FLIGHT_S`` may still be on its way, so it is looked at again that much later; then the window moves
        on to the last time the DMO's answer holds."""
        since, recent = self.seen.since, time.time_ns() - IN_FLIGHT_S * 1e9
        added, late, latest = 0, [], None
        self._answered.clear()
        for entry in self.bus.replies(f"{self.bus.keys.everything()}?{HISTORY};{SINCE}={since}", HISTORY_TIMEOUT_S):
            if entry[2] is None:
                continue
            latest = entry[2] if latest is None else max(latest, entry[2])
            if entry[2] < recent:  # each reply as it comes: a day's traffic is never held here whole
                added += self._queue_missing((entry,))
            else:
                late.append(entry)
        if latest is None:  # nobody answered (a day summary is in any answer): the window stays where it was
            return 0
        self._answered.set()
        if late:
            self._closed.wait(IN_FLIGHT_S)
        added += self._queue_missing(late)
        self.seen.checked_until(latest + 1)
        if added:
            log.info("caught up on %d message(s) the DMO sent or received since the last check that never came "
                     "here", added)
        return added

    def _queue_missing(self, entries) -> int:
        """Queue, with the DMO's time, each entry not queued before; return how many."""
        added = 0
        for key, payload, at in entries:
            with self._live_lock:
                missing = (key, payload) not in self.seen
                if missing:
                    self.seen.add(key, payload)
            if missing:
                self._queue.put((key, payload, at, False))
                added += 1
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
                self.seen.add(key, payload)
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
            self._finish_catching_up()
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                self._write(*item, on_write)
            self._next_window()
            if self.dropped:
                writer.add_metadata(DROPPED_METADATA, self.dropped)
            writer.close()
            self.stop()

    def _finish_catching_up(self) -> None:
        """Let a check of the DMO's history under way end (its answer may hold the last registrations the file
        lacks, or the last statements, which a DMO that has left at once answered just before), for at most
        ``CLOSING_WAIT_S`` while the DMO is there to answer or its answer is in; then no new one starts."""
        self._closed.set()
        thread = self._catching_up
        if thread is not None and thread is not threading.current_thread():
            self._wake.set()
            thread.join(CLOSING_WAIT_S if self._answered.is_set() or not self._dmo_gone.is_set() else 0)

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


def _short(digest: bytes) -> int:
    return int.from_bytes(digest[:8], "little")


def _digest(key: str, payload: bytes) -> bytes:
    digest = hashlib.blake2b(key.encode(), digest_size=16)
    digest.update(b"\0")
    digest.update(payload)
    return digest.digest()


def _parsed(key: str):
    try:
        return parse_key(key)
    except ValueError:  # a key outside the layout: recorded, never caught up
        return None
