"""The day's incidents (late, missing or vanished agents, rejected messages), capped so that a flood of bad
messages cannot swell the day summary past its limit.

Each rejection is an incident, up to ``MAX_LISTED_REJECTIONS``; beyond, rejections are only counted (each is still
published on ``dmo/rejected`` with its reason). The list never exceeds ``MAX_INCIDENTS``, the day summary's limit.
"""

from __future__ import annotations

import collections

from messages import Incident

MAX_LISTED_REJECTIONS = 200
MAX_INCIDENTS = 10_000
MAX_REASON = 500


class IncidentLog:
    """Incidents in the order they happened, and every rejection counted by code."""

    def __init__(self):
        self.incidents: list[Incident] = []
        self.rejected = 0
        self.rejected_by_code: collections.Counter[str] = collections.Counter()

    def add(self, agent: str | None, phase: str, hour: int | None, reason: str) -> Incident:
        self.incidents.append(Incident(agent=agent, phase=phase, hour=hour, reason=reason[:MAX_REASON]))
        return self.incidents[-1]

    def count_rejection(self, code: str) -> bool:
        """Count one rejection; whether it is still to be listed as an incident."""
        self.rejected += 1
        self.rejected_by_code[code] += 1
        return self.rejected <= MAX_LISTED_REJECTIONS

    def close(self, phase: str, hour: int | None) -> list[Incident]:
        """At settlement: say how many rejections were not listed, and cut the list to ``MAX_INCIDENTS``. Returns
        the incidents this added."""
        added = []
        if self.rejected > MAX_LISTED_REJECTIONS:
            by_code = ", ".join(f"{code} {n}" for code, n in sorted(self.rejected_by_code.items()))
            added.append(self.add(None, phase, hour, f"{self.rejected} messages rejected in all ({by_code}); only the "
                                                     f"first {MAX_LISTED_REJECTIONS} are listed here, each is on "
                                                     "dmo/rejected with its reason"))
        if len(self.incidents) > MAX_INCIDENTS:
            extra = len(self.incidents) - MAX_INCIDENTS + 1
            del self.incidents[MAX_INCIDENTS - 1:]
            added.append(self.add(None, phase, hour, f"{extra} more incidents not listed (see the DMO's log)"))
        return added
