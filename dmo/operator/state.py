"""What the DMO has accepted so far in its day, and where the run stands; only the DMO's main thread touches it."""

from __future__ import annotations

import collections
import copy
import datetime as dt
from dataclasses import dataclass, field

from messages import Bid, Incident, Registration, Schedule

from .guard import SequenceGuard
from .incidents import IncidentLog


@dataclass
class DayState:
    """The accepted answers of each agent, presence, the replay guard and the incident log.

    ``run_token`` is the run's token, drawn when the run starts (kept in the journal for a resumed DMO): every
    message of the run carries it.
    ``meter`` maps an agent to {hour index 0..23: P_M per sub-period}; ``realised`` an agent to the market days of
    the realised days it reported (of the run: one may come after the next day began, and none changes a settlement;
    the days themselves go to the run's result, on disk: finished.py);
    ``vanished`` maps an agent whose liveliness was lost to the (phase, hour) it vanished in (it may come back);
    ``gone`` holds the agents not live now. Registrations, presence, realised days and the replay guard belong to
    the run; the answers, incidents and counts to the day ``day`` (1-based), whose date is ``market_day``: ``start_day`` closes one day and opens the next.
    """

    registered: dict[str, Registration] = field(default_factory=dict)
    gone: set[str] = field(default_factory=set)
    bids: dict[str, Bid] = field(default_factory=dict)
    schedules: dict[str, Schedule] = field(default_factory=dict)
    meter: dict[str, dict[int, tuple[float, ...]]] = field(default_factory=dict)
    realised: dict[str, set[str]] = field(default_factory=dict)
    log: IncidentLog = field(default_factory=IncidentLog)
    accepted: collections.Counter = field(default_factory=collections.Counter)  # by kind
    guard: SequenceGuard = field(default_factory=SequenceGuard)
    vanished: dict[str, tuple[str, int | None]] = field(default_factory=dict)
    rescheduling: set[str] = field(default_factory=set)  # rejoined agents whose new schedule is awaited
    again: int = 0  # exact copies of accepted messages received (sent again for want of a receipt), this day
    dropped: collections.Counter = field(default_factory=collections.Counter)  # agent -> over its budget, this day
    run_token: str = ""
    phase: str = "registration"
    hour: int | None = None
    day: int = 1
    market_day: str = ""

    def start_day(self, day: int, market_day: str) -> DayState:
        """Close the current day and open ``day``: returns the closed day's state (its answers, incidents and
        counts, for its result); registrations, presence, realised days and the replay guard carry over."""
        closed = copy.copy(self)
        self.day, self.market_day, self.phase, self.hour = day, market_day, "bidding", None
        self.bids, self.schedules, self.rescheduling = {}, {}, set()
        self.meter = {agent: {} for agent in self.registered}
        self.log, self.accepted, self.again = IncidentLog(), collections.Counter(), 0
        self.dropped = collections.Counter()
        return closed

    @property
    def first_market_day(self) -> str:
        """The date of the run's first day."""
        return (dt.date.fromisoformat(self.market_day) - dt.timedelta(days=self.day - 1)).isoformat()

    def live(self) -> list[str]:
        return sorted(a for a in self.registered if a not in self.gone)

    def count_accepted(self, msg, sha256: str) -> None:
        """An accepted message, whose payload hashes to ``sha256``: from now on a copy of it is that message again,
        and anything older from its sender, or another payload under its number, is refused."""
        if isinstance(msg, Registration) and self.guard.incarnation.get(msg.sender) != msg.incarnation:
            self.guard.admit(msg.sender, msg.incarnation)  # its first registration, or its rejoin
        self.guard.accept(msg.sender, msg.seq, sha256)
        self.accepted[msg.kind] += 1

    @property
    def incidents(self) -> list[Incident]:
        return self.log.incidents

    @property
    def rejected(self) -> int:
        return self.log.rejected

    @property
    def rejected_by_code(self) -> collections.Counter:
        return self.log.rejected_by_code
