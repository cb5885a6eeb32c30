"""Republish recorded traffic over Zenoh: payloads as recorded, on the same keys under a new run prefix, with their
original spacing scaled by a rate (or as fast as Zenoh takes them).

Messages go out in log-time order (the order the recorder received them). Publishers use congestion control
BLOCK: a fast replay slows down rather than drops. A payload the recorder filed as invalid is replayed as it
arrived, on its original key, so a recorded fault replays as the same fault.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from typing import Callable, Sequence

import zenoh

from ..keys import key_pattern
from .reader import RecordedMessage, Recording


def select(rec: Recording, patterns: Sequence[str] = (), start_offset_s: float = 0.0,
           market_day: str | None = None) -> list[RecordedMessage]:
    """The messages to replay, in log-time order: those on keys matching any pattern (all if none), of
    ``market_day`` if given (the day a payload says it is of; one that says none is left out), from
    ``start_offset_s`` seconds after the first of them."""
    ordered = rec.in_log_order()
    if market_day is not None:
        ordered = [m for m in ordered if _market_day(m.payload) == market_day]
    if not ordered:
        return []
    compiled = [key_pattern(p) for p in patterns]
    start = ordered[0].log_time + round(start_offset_s * 1e9)
    return [m for m in ordered if m.log_time >= start and (not compiled or any(p.match(m.relative_key) for p in compiled))]


def _market_day(payload: bytes) -> str | None:
    try:
        data = json.loads(payload)
    except ValueError:
        return None
    return data.get("market_day") if isinstance(data, dict) else None


@dataclass
class PlayStats:
    published: int = 0
    loops: int = 0
    seconds: float = 0.0


class Player:
    """Publishes recorded messages on an open Bus, under that bus's run prefix."""

    def __init__(self, bus, messages: Sequence[RecordedMessage]):
        self.bus, self.messages = bus, list(messages)
        self._publishers: dict[str, zenoh.Publisher] = {}

    def key(self, m: RecordedMessage) -> str:
        return f"{self.bus.keys.prefix}/{m.relative_key}"

    def publish(self, m: RecordedMessage) -> None:
        key = self.key(m)
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self.bus.session.declare_publisher(
                key, encoding=zenoh.Encoding.APPLICATION_JSON, congestion_control=zenoh.CongestionControl.BLOCK)
        publisher.put(m.payload)

    def wait_for_subscriber(self, timeout_s: float) -> bool:
        return bool(self.messages) and timeout_s > 0 and self.bus.wait_for_subscribers(self.key(self.messages[0]),
                                                                                     timeout_s)

    def play(self, rate: float, stop: threading.Event, loop: bool = False,
             on_message: Callable[[RecordedMessage], None] | None = None) -> PlayStats:
        """Publish every message, the n-th at (its log time - the first's) / rate after the start; ``rate`` 0
        publishes as fast as Zenoh accepts. With ``loop``, start over until ``stop`` is set."""
        stats = PlayStats()
        start = time.perf_counter()
        while self.messages and not stop.is_set():
            t0, base = time.perf_counter(), self.messages[0].log_time
            for m in self.messages:
                if rate:
                    delay = t0 + (m.log_time - base) / 1e9 / rate - time.perf_counter()
                    if delay > 0 and stop.wait(delay):
                        break
                elif stop.is_set():
                    break
                self.publish(m)
                stats.published += 1
                if on_message is not None:
                    on_message(m)
            else:
                stats.loops += 1
            if not loop:
                break
        stats.seconds = time.perf_counter() - start
        return stats

    def drain(self, linger_s: float = 0.5) -> None:
        """Give Zenoh time to send what it has queued: closing a session drops what is still in its queues."""
        time.sleep(linger_s)

    def close(self) -> None:
        for publisher in self._publishers.values():
            try:
                publisher.undeclare()
            except Exception:  # the session may be closing already
                pass
        self._publishers.clear()

    def __enter__(self) -> Player:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["PlayStats", "Player", "key_pattern", "select"]
