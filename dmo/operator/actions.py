"""What the DMO's machine asks of its driver (machine.py): each action one small typed value. ``handle`` returns
the actions in order, the last one a request (``Wait``, ``CheckPresence``, ``OpenWindow``) whose answer is the
next event the driver gives, or ``Stop``."""

from __future__ import annotations

from dataclasses import dataclass

from messages import Message
from messages.schemas import AgentDay

from .report import DayReport


@dataclass(frozen=True)
class Publish:
    """Put ``msg`` (not stamped yet: the driver gives it the run's token, its number and its time) on its key."""

    msg: Message


@dataclass(frozen=True)
class Journaled:
    """Append ``entry`` to the DMO's journal (journal.py), if it keeps one, before anything that follows."""

    entry: dict


@dataclass(frozen=True)
class Settled:
    """A day's report (``DayResult.report``), for the run's result: the driver keeps it (on disk: finished.py)."""

    report: DayReport


@dataclass(frozen=True)
class Realised:
    """An agent's realised day the DMO took, for the run's result."""

    msg: AgentDay


@dataclass(frozen=True)
class Wait:
    """Give the machine the events that come, until nobody is ``waiting`` any more (the machine says so by its
    next action). ``until`` is the deadline on the driver's clock (``inf``: none, on the logical clock; ``-inf``:
    only what is queued already): then ``TimedOut``. ``what`` the DMO waits for, and from whom, is for the driver to
    say while it waits."""

    what: str
    waiting: tuple[str, ...]
    until: float


@dataclass(frozen=True)
class CheckPresence:
    """Which of ``names`` have a process there: asked once, each question taking at most ``query_s``, and asked
    again until all are there or ``wait_s`` have passed. Answered by ``Present``."""

    names: tuple[str, ...]
    query_s: float
    wait_s: float = 0.0


@dataclass(frozen=True)
class OpenWindow:
    """A new phase or hour: every agent's budget starts afresh. Answered by ``Dropped`` (what the closed window
    dropped of each)."""


@dataclass(frozen=True)
class Stop:
    """The run is over; its result is the machine's ``result``."""


Action = Publish | Journaled | Settled | Realised | Wait | CheckPresence | OpenWindow | Stop
Request = Wait | CheckPresence | OpenWindow | Stop
