"""At-least-once delivery of what an agent sends the DMO: each payload is sent again, byte for byte, until the
DMO's receipt for it comes (docs/protocol.md, "Receipts and sending again").

A lost registration, bid, schedule or meter report is thus recovered within a second or so instead of being
waited out to its phase's deadline; the DMO takes an exact copy of a payload it accepted as that payload again, so
sending one twice is harmless. The resends run on a thread of their own, so an agent busy solving its schedule
still resends what is waiting for a receipt. When to send again is ``Resends``, when a silent agent asks the DMO
again ``Silence``, and when a joining agent asks it again for its clock ``Joining``: pure policies, given the time.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Callable

from messages import Message, Receipt, sha256

log = logging.getLogger("dmosim.agent")

FIRST_RESEND_S = 0.5  # a receipt normally comes within milliseconds on one host, tens of them across hosts
MAX_RESEND_S = 4.0    # the wait between resends doubles up to this (a DMO restarting takes seconds to listen)
MIN_WAIT_S = 0.05     # the shortest wait of a silent agent before it looks again whether it has heard anything

Put = Callable[[str, bytes], None]  # (key, payload): sends one payload again


@dataclass(frozen=True)
class RefusedPayload:
    """The DMO's receipt refusing a payload the agent sent: the receipt (its code and reason) and what it was."""

    receipt: Receipt
    kind: str
    seq: int


@dataclass
class Pending:
    """A payload awaiting its receipt: where it goes, what it is, and when it is sent again (``due``, after
    ``wait`` seconds since the last time)."""

    key: str
    payload: bytes
    kind: str
    seq: int
    due: float
    wait: float


class Resends:
    """When each payload awaiting its receipt is sent again: ``first_s`` after it was sent, then at doubling
    intervals up to ``max_s``. Pure: the caller gives the time (``now``), so the policy is the same on any clock."""

    def __init__(self, first_s: float = FIRST_RESEND_S, max_s: float = MAX_RESEND_S):
        self.first_s, self.max_s = first_s, max_s
        self.pending: dict[str, Pending] = {}  # payload's sha256 -> it

    def sent(self, key: str, payload: bytes, kind: str, seq: int, now: float) -> None:
        self.pending[sha256(payload)] = Pending(key, payload, kind, seq, now + self.first_s, self.first_s)

    def receipt(self, payload_sha256: str) -> Pending | None:
        """Its receipt came: the payload is no longer sent again; the payload, or None if none awaited it."""
        return self.pending.pop(payload_sha256, None)

    def due(self, now: float) -> list[Pending]:
        """The payloads to send again now, each next due after twice its last wait (at most ``max_s``)."""
        due = [p for p in self.pending.values() if p.due <= now]
        for p in due:
            p.wait = min(2 * p.wait, self.max_s)
            p.due = now + p.wait
        return due

    def next_due(self) -> float | None:
        """When the next payload is due again (None: nothing awaits a receipt)."""
        return min((p.due for p in self.pending.values()), default=None)


class Silence:
    """How long an agent that hears nothing from the DMO waits before it asks the DMO again for what it waits for
    (a message of it may have been lost): ``first_s``, then twice as long after each time it asks, up to ``max_s``;
    it gives up once ``idle_s`` have passed since it last heard anything (``since``). Pure: given the time."""

    def __init__(self, idle_s: float, since: float, first_s: float, max_s: float):
        self.idle_s, self.since, self.wait, self.max_s = idle_s, since, first_s, max_s

    def over(self, now: float) -> bool:
        """Whether the agent has heard nothing for ``idle_s``: it gives up."""
        return now - self.since >= self.idle_s

    def asked(self, now: float) -> float:
        """The agent has asked (at ``now``): how long to wait before it asks again, never past giving up."""
        self.wait = min(2 * self.wait, self.max_s, max(MIN_WAIT_S, self.since + self.idle_s - now))
        return self.wait


class Joining:
    """How an agent that joins asks the DMO for its clock until it answers: each query waits ``wait`` for the answer,
    ``first_s`` at first. A query that waited all that time unanswered found the DMO there but busy (a thousand agents
    joining): the next one waits twice as long, up to ``max_s``. One that found nobody at once found it not up yet:
    the next one goes after ``pause_s``. The agent gives up ``idle_s`` after it began (``since``). Pure: given the
    time."""

    def __init__(self, idle_s: float, since: float, first_s: float, max_s: float, pause_s: float):
        self.deadline, self.wait, self.max_s, self.pause_s = since + idle_s, first_s, max_s, pause_s

    def unanswered(self, asked: float, now: float) -> float | None:
        """The query asked at ``asked`` had no answer by ``now``: how long to pause before the next one, or None to
        give up."""
        if now >= self.deadline:
            return None
        if now - asked >= self.wait:
            self.wait = min(2 * self.wait, self.max_s)
            return 0.0
        return self.pause_s


class Delivery:
    """The payloads awaiting their receipt, sent again by ``put`` on a thread of its own as ``Resends`` says, on the
    monotonic clock. Thread-safe; ``close`` stops it."""

    def __init__(self, put: Put, first_s: float = FIRST_RESEND_S, max_s: float = MAX_RESEND_S):
        self._put = put
        self._resends = Resends(first_s, max_s)
        self._lock = threading.Condition()
        self._closed = False
        self.resent = 0
        self._thread = threading.Thread(target=self._loop, name="delivery", daemon=True)
        self._thread.start()

    def sent(self, key: str, payload: bytes, stamped: Message) -> None:
        """A payload about to be published (``Bus.publish``'s ``before_put``, so that its receipt cannot come
        first): it is sent again until its receipt comes."""
        with self._lock:
            self._resends.sent(key, payload, stamped.kind, stamped.seq, time.monotonic())
            self._lock.notify_all()

    def receipt(self, receipt: Receipt) -> tuple[str, int] | None:
        """A receipt came: its payload is no longer sent again. Returns the (kind, seq) it was, None if it names no
        payload awaiting one (a receipt of a copy, or of a payload someone else sent in this agent's name)."""
        with self._lock:
            pending = self._resends.receipt(receipt.payload_sha256)
            self._lock.notify_all()
        return None if pending is None else (pending.kind, pending.seq)

    def drained(self, timeout_s: float) -> bool:
        """Wait until every payload sent has its receipt (or ``timeout_s`` passes); whether they all have."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._resends.pending and (left := deadline - time.monotonic()) > 0:
                self._lock.wait(timeout=left)
            return not self._resends.pending

    def waiting(self) -> int:
        with self._lock:
            return len(self._resends.pending)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._lock.notify_all()
        self._thread.join(timeout=5)

    def _loop(self) -> None:
        while True:
            with self._lock:
                if self._closed:
                    return
                now = time.monotonic()
                due = self._resends.due(now)
                if not due:
                    nearest = self._resends.next_due()
                    self._lock.wait(timeout=None if nearest is None else max(0.0, nearest - now))
                    continue
            for p in due:  # outside the lock: a put may block on the network
                try:
                    self._put(p.key, p.payload)
                    self.resent += 1
                    log.info("sent %s #%d again: no receipt yet", p.kind, p.seq)
                except Exception as exc:  # the session is closing: nothing more can be sent
                    log.info("could not send %s #%d again: %s", p.kind, p.seq, exc)
