"""The part of a run that is over, kept on disk until the run's result is made: each day's report once the day is
settled, and each realised day an agent reported, so that the DMO does not grow with the days of a run.

A settled day's bids, schedules, meter reports and statements, and the agents' realised days, are what a long run
would otherwise pile up in the DMO (about 0.1 MiB per agent and day as Python objects). Later days need none of
them: what they need (the agents registered, the market days each agent has reported, the replay guard) stays in
``DayState``, and settlement and replay read the recording or the journal. The file is a temporary one that goes
with the process.
"""

from __future__ import annotations

import json
import tempfile

from messages.schemas import AgentDay, Envelope

from .report import DayReport

ENVELOPE = frozenset(Envelope.model_fields)  # what a realised day is reported without: the run's result says whose


class FinishedDays:
    """JSON lines in a temporary file, written by the DMO's main thread: ``{"day": report}`` for each day settled,
    ``{"realised": agent, "market_day": ..., "reported": ...}`` for each realised day accepted. ``read`` once, at
    the end of the run."""

    def __init__(self):
        self._file = tempfile.TemporaryFile("w+", encoding="utf-8")  # noqa: SIM115  (closed by read)

    def day(self, report: DayReport) -> None:
        """A settled day, as ``DayResult.report`` gives it."""
        self._write({"day": report.model_dump(mode="json")})

    def realised(self, msg: AgentDay) -> None:
        """A realised day the DMO accepted."""
        self._write({"realised": msg.sender, "market_day": msg.market_day,
                     "reported": msg.model_dump(exclude=set(ENVELOPE))})

    def read(self) -> tuple[list[DayReport], dict[str, dict[str, dict]]]:
        """Every day's report in the order written, and agent -> market day -> its realised day as reported (without
        the envelope); the file is closed."""
        days: list[DayReport] = []
        realised: dict[str, dict[str, dict]] = {}
        self._file.seek(0)
        for line in self._file:
            entry = json.loads(line)
            if "day" in entry:
                days.append(DayReport.model_validate(entry["day"]))
            else:
                realised.setdefault(entry["realised"], {})[entry["market_day"]] = entry["reported"]
        self._file.close()
        return days, realised

    def _write(self, entry: dict) -> None:
        self._file.write(json.dumps(entry, separators=(",", ":")) + "\n")
