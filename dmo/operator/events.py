"""What happens to the DMO's day, as it is told: each event one small typed value, made on Zenoh's threads and
handled in order on the DMO's own (day.py)."""

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


Event = Received | Unreadable | Joined | Left | OverBudget
