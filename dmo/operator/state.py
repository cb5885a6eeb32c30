"""What the DMO has accepted so far in its day, and where the day stands; only the DMO's main thread touches it."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

from messages import Bid, Incident, Registration, Schedule

from .guard import SequenceGuard
from .incidents import IncidentLog


@dataclass
class DayState:
    """The accepted answers of each agent, presence, the replay guard and the incident log.

    ``meter`` maps an agent to {hour index 0..23: P_M per sub-period}; ``vanished`` maps an agent whose liveliness
    was lost to the (phase, hour) it vanished in (it may come back); ``gone`` holds the agents not live now.
    """

    registered: dict[str, Registration] = field(default_factory=dict)
    gone: set[str] = field(default_factory=set)
    bids: dict[str, Bid] = field(default_factory=dict)
    schedules: dict[str, Schedule] = field(default_factory=dict)
    meter: dict[str, dict[int, tuple[float, ...]]] = field(default_factory=dict)
    log: IncidentLog = field(default_factory=IncidentLog)
    accepted: collections.Counter = field(default_factory=collections.Counter)  # by kind
    guard: SequenceGuard = field(default_factory=SequenceGuard)
    vanished: dict[str, tuple[str, int | None]] = field(default_factory=dict)
    rescheduling: set[str] = field(default_factory=set)  # rejoined agents whose new schedule is awaited
    phase: str = "registration"
    hour: int | None = None

    def live(self) -> list[str]:
        return sorted(a for a in self.registered if a not in self.gone)

    def count_accepted(self, msg) -> None:
        """An accepted message: a copy of it, or anything older from its sender, is refused from now on."""
        self.guard.accept(msg.sender, msg.seq)
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
