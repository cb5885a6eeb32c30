"""At-least-once delivery of what an agent sends the DMO: each payload is sent again, byte for byte, until the
DMO's receipt for it comes (docs/protocol.md, "Receipts and sending again").

A lost registration, bid, schedule or meter report is thus recovered within a second or so instead of being
waited out to its phase's deadline; the DMO takes an exact copy of a payload it accepted as that payload again, so
sending one twice is harmless. The resends run on a thread of their own, so an agent busy solving its schedule
still resends what is waiting for a receipt.
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

Put = Callable[[str, bytes], None]  # (key, payload): sends one payload again


@dataclass
class _Pending:
    key: str
    payload: bytes
    kind: str
    seq: int
    due: float
    wait: float


class Delivery:
    """The payloads awaiting their receipt, sent again by ``put`` until it comes. Thread-safe; ``close`` stops it."""

    def __init__(self, put: Put, first_s: float = FIRST_RESEND_S, max_s: float = MAX_RESEND_S):
        self._put, self._first, self._max = put, first_s, max_s
        self._pending: dict[str, _Pending] = {}
        self._lock = threading.Condition()
        self._closed = False
        self.resent = 0
        self._thread = threading.Thread(target=self._loop, name="delivery", daemon=True)
        self._thread.start()

    def sent(self, key: str, payload: bytes, stamped: Message) -> None:
        """A payload about to be published (``Bus.publish``'s ``before_put``, so that its receipt cannot come
        first): it is sent again until its receipt comes."""
        with self._lock:
            self._pending[sha256(payload)] = _Pending(key, payload, stamped.kind, stamped.seq,
                                                      time.monotonic() + self._first, self._first)
            self._lock.notify_all()

    def receipt(self, receipt: Receipt) -> tuple[str, int] | None:
        """A receipt came: its payload is no longer sent again. Returns the (kind, seq) it was, None if it names no
        payload awaiting one (a receipt of a copy, or of a payload someone else sent in this agent's name)."""
        with self._lock:
            pending = self._pending.pop(receipt.payload_sha256, None)
            self._lock.notify_all()
        return None if pending is None else (pending.kind, pending.seq)

    def drained(self, timeout_s: float) -> bool:
        """Wait until every payload sent has its receipt (or ``timeout_s`` passes); whether they all have."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            while self._pending and (left := deadline - time.monotonic()) > 0:
                self._lock.wait(timeout=left)
            return not self._pending

    def waiting(self) -> int:
        with self._lock:
            return len(self._pending)

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
                due = [p for p in self._pending.values() if p.due <= now]
                for p in due:
                    p.wait = min(2 * p.wait, self._max)
                    p.due = now + p.wait
                if not due:
                    nearest = min((p.due for p in self._pending.values()), default=now + 3600)
                    self._lock.wait(timeout=max(0.0, nearest - now))
                    continue
            for p in due:  # outside the lock: a put may block on the network
                try:
                    self._put(p.key, p.payload)
                    self.resent += 1
                    log.info("sent %s #%d again: no receipt yet", p.kind, p.seq)
                except Exception as exc:  # the session is closing: nothing more can be sent
                    log.info("could not send %s #%d again: %s", p.kind, p.seq, exc)
