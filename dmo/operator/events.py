"""What happens to the DMO's day, as its machine is told (machine.py): each event one small typed value, made by a
driver (on Zenoh's threads, by the in-process market, or from a recording) and handled in order."""

from __future__ import annotations

from dataclasses import dataclass

from messages import Message, MessageError


@dataclass(frozen=True)
class Received:
    """A valid message from an agent, with the bytes it came as."""

    key: str
    msg: Message
    payload: bytes


@dataclass(frozen=True)
class Unreadable:
    """A payload on an agent's key that is no valid message (``error`` says why)."""

    key: str
    payload: bytes
    error: MessageError


@dataclass(frozen=True)
class Joined:
    """A process of the run announced itself (its liveliness token appeared)."""

    name: str


@dataclass(frozen=True)
class Left:
    """A process of the run is gone (its liveliness token went: it closed, died, or its lease lapsed)."""

    name: str


@dataclass(frozen=True)
class OverBudget:
    """An agent went over its budget in this phase or hour: what it sends more is dropped unread. (None: keys that
    name no valid agent, which share one budget.)"""

    agent: str | None


@dataclass(frozen=True)
class TimedOut:
    """What the machine waited for (``Wait``) did not all come by its deadline; or, for a wait without one, nothing
    more is queued."""


@dataclass(frozen=True)
class Present:
    """The answer to ``CheckPresence``: those of the names asked about whose process is there."""

    names: frozenset[str]


@dataclass(frozen=True)
class Dropped:
    """The answer to ``OpenWindow``: how many messages of each agent the window that closed dropped unread, its
    budget spent (None: keys that name no valid agent)."""

    counts: dict[str | None, int]


Event = Received | Unreadable | Joined | Left | OverBudget | TimedOut | Present | Dropped
