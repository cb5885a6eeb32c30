"""Message faults injected at the sender's Bus: drop, delay, duplicate or corrupt what it publishes on matching keys.

A fault spec is ``KIND:PATTERN:VALUE``, PATTERN a key pattern relative to the run prefix as ``dmosim replay
--topics`` reads it (``*`` within one level, ``**`` across levels, e.g. ``agent/*/meter``, ``dmo/grid``,
``agent/mg2/**``):

    drop:PATTERN:P              lose each matching message with probability P
    duplicate:PATTERN:P         publish it twice with probability P (same payload, same seq)
    corrupt:PATTERN:P           replace its payload, with probability P, by bytes that no receiver can accept
    delay:PATTERN:SECONDS[:P]   publish it SECONDS later (with probability P, default 1), on a timer thread

Each process applies the specs to its own publications only, drawing from a generator seeded by the run's seed
and the process name, so a run with the same seed injects the same faults. Several specs may match one message:
a drop wins; otherwise a corruption replaces the payload, a duplicate doubles it, and the longest delay applies.
A corrupted payload is always refused by the receiver (not JSON, or not a valid message), never read as a
different valid message: that is what a checksum guarantees on a real network.
"""

from __future__ import annotations

import collections
import logging
import random
import re
import threading
from dataclasses import dataclass
from typing import Callable

from ..codec import MessageError, decode
from ..keys import key_pattern

log = logging.getLogger(__name__)

MESSAGE_FAULTS = ("drop", "delay", "duplicate", "corrupt")
MAX_DELAY_S = 3600.0
_PATTERN = re.compile(r"^[A-Za-z0-9_*?-]+(/[A-Za-z0-9_*?-]+)*$")

Put = Callable[[str, bytes], None]  # (key, payload): what the Bus does to send one payload


class FaultSpecError(ValueError):
    """A fault spec that cannot be used; the message is one line naming the problem."""


@dataclass(frozen=True)
class MessageFault:
    kind: str          # drop | delay | duplicate | corrupt
    pattern: str       # glob relative to the run prefix
    probability: float
    delay_s: float = 0.0

    def __str__(self) -> str:
        if self.kind == "delay":
            return f"delay:{self.pattern}:{self.delay_s:g}" + (f":{self.probability:g}" if self.probability < 1 else "")
        return f"{self.kind}:{self.pattern}:{self.probability:g}"

    def matches(self, relative_key: str) -> bool:
        if self.pattern not in _PATTERNS:
            _PATTERNS[self.pattern] = key_pattern(self.pattern)
        return _PATTERNS[self.pattern].match(relative_key) is not None


_PATTERNS: dict[str, re.Pattern] = {}


def parse_message_fault(text: str) -> MessageFault:
    """Parse ``drop|duplicate|corrupt:PATTERN:P`` or ``delay:PATTERN:SECONDS[:P]``; FaultSpecError if malformed."""
    parts = str(text).split(":")
    kind = parts[0]
    if kind not in MESSAGE_FAULTS:
        raise FaultSpecError(f"unknown message fault {kind!r} in {text!r} "
                             f"(message faults: {', '.join(MESSAGE_FAULTS)})")
    usage = "delay:PATTERN:SECONDS[:P]" if kind == "delay" else f"{kind}:PATTERN:P"
    if len(parts) not in ((3, 4) if kind == "delay" else (3,)):
        raise FaultSpecError(f"fault {text!r}: expected {usage}")
    pattern = parts[1]
    if not _PATTERN.match(pattern):
        raise FaultSpecError(f"fault {text!r}: PATTERN must be a key relative to the run prefix, levels of letters, "
                             "digits, _ and - with * (within a level) or ** (across levels), e.g. agent/*/meter")
    if kind == "delay":
        delay = _number(text, parts[2], "SECONDS", 0.0, MAX_DELAY_S)
        probability = _number(text, parts[3], "P", 0.0, 1.0) if len(parts) == 4 else 1.0
        return MessageFault(kind, pattern, probability, delay)
    return MessageFault(kind, pattern, _number(text, parts[2], "P", 0.0, 1.0))


def _number(text: str, value: str, name: str, low: float, high: float) -> float:
    try:
        x = float(value)
    except ValueError:
        x = float("nan")
    if not low <= x <= high:  # also refuses nan
        raise FaultSpecError(f"fault {text!r}: {name} must be a number in [{low:g}, {high:g}], got {value!r}")
    return x


def corrupt(payload: bytes, rng: random.Random) -> bytes:
    """Damage a payload so that no receiver accepts it: flip a few bytes, cut it short or break its encoding.

    A flipped byte can turn one digit into another and leave a valid message that means something else; such
    a result is never sent: the payload is then cut short instead, which no JSON object survives."""
    data = bytearray(payload)
    how = rng.randrange(3)
    if how == 0 and data:
        for _ in range(1 + rng.randrange(3)):
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
    elif how == 1 and data:
        data.insert(rng.randrange(len(data) + 1), 0xFF)  # never valid UTF-8
    else:
        return bytes(payload[:rng.randrange(max(1, len(payload)))])
    out = bytes(data)
    try:
        decode(out)
    except MessageError:
        return out
    return bytes(payload[:rng.randrange(max(1, len(payload)))])


class FaultInjector:
    """Applies message faults to one process's publications. ``prefix`` is the run's key prefix; ``seed`` and
    ``name`` seed the draws. ``injected`` counts what was done, by fault kind."""

    def __init__(self, faults: list[MessageFault] | tuple[MessageFault, ...], prefix: str, seed: int = 0,
                 name: str = ""):
        self.faults = tuple(faults)
        self.prefix = prefix.rstrip("/") + "/"
        self._rng = random.Random(f"{seed}:{name}")
        self._lock = threading.Lock()
        self._timers: set[threading.Timer] = set()
        self.injected: collections.Counter[str] = collections.Counter()

    def send(self, key: str, payload: bytes, put: Put) -> None:
        """Send ``payload`` on ``key`` through ``put``, with whatever faults fire for it."""
        relative = key[len(self.prefix):] if key.startswith(self.prefix) else key
        drop = dup = False
        delay = 0.0
        with self._lock:  # one generator, drawn in publication order: reproducible for a given seed
            for f in self.faults:
                if not f.matches(relative) or self._rng.random() >= f.probability:
                    continue
                self.injected[f.kind] += 1
                if f.kind == "drop":
                    drop = True
                elif f.kind == "duplicate":
                    dup = True
                elif f.kind == "delay":
                    delay = max(delay, f.delay_s)
                else:
                    payload = corrupt(payload, self._rng)
        if drop:
            log.info("fault: dropped a message on %s", relative)
            return
        copies = 2 if dup else 1
        if delay <= 0:
            for _ in range(copies):
                put(key, payload)
            return
        timer = threading.Timer(delay, self._late, (key, payload, copies, put))
        timer.daemon = True  # a delayed message never keeps a finished process alive
        with self._lock:
            self._timers.add(timer)
        timer.start()

    def _late(self, key: str, payload: bytes, copies: int, put: Put) -> None:
        with self._lock:
            self._timers = {t for t in self._timers if t.is_alive() and t is not threading.current_thread()}
        try:
            for _ in range(copies):
                put(key, payload)
        except Exception as exc:  # the bus closed meanwhile: the message is lost, as it would be on a network
            log.info("fault: delayed message on %s not sent: %s", key, exc)

    def cancel(self) -> None:
        """Forget the delayed messages still pending (the bus is closing)."""
        with self._lock:
            timers, self._timers = self._timers, set()
        for t in timers:
            t.cancel()

    def summary(self) -> dict[str, int]:
        with self._lock:
            return dict(self.injected)


def injector(specs: list[str] | tuple[str, ...], prefix: str, seed: int, name: str) -> FaultInjector | None:
    """A FaultInjector for the message faults among ``specs`` (other kinds, e.g. kill, are skipped), or None."""
    faults = [parse_message_fault(s) for s in specs if s.split(":", 1)[0] in MESSAGE_FAULTS]
    return FaultInjector(faults, prefix, seed, name) if faults else None
