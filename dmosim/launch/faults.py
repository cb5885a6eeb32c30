"""Process faults of ``dmosim run --fault``: an agent killed or restarted, the DMO restarted or the recorder killed,
when the DMO's clock reaches an hour. Message faults (drop, delay, duplicate, corrupt) are injected at each role's bus instead
(messages/transport/faults.py); ``parse_fault`` reads either (docs/faults.md)."""

from __future__ import annotations

from dataclasses import dataclass

from messages.transport.faults import MESSAGE_FAULTS, FaultSpecError, MessageFault, parse_message_fault
from scenarios.horizon import HOURS

PROCESS_FAULTS = ("kill", "restart")


@dataclass(frozen=True)
class Fault:
    """``kill:AGENT:HOUR[:DAY]``: SIGKILL the agent's process when the DMO's clock reaches that hour of that day (of
    day 1 if none is given); ``restart:AGENT:HOUR[:DAY]`` also starts it again at once, with the same command line
    (it registers again and rejoins the day). AGENT may also be ``dmo`` (restart only: it resumes from its journal)
    or ``recorder`` (kill only: the run goes on without it)."""

    agent: str
    hour: int
    kind: str = "kill"
    day: int = 1

    def __str__(self) -> str:
        return f"{self.kind}:{self.agent}:{self.hour}" + (f":{self.day}" if self.day != 1 else "")


def parse_fault(text: str) -> Fault | MessageFault:
    """A process fault (kill, restart) or a message fault (drop, delay, duplicate, corrupt); FaultSpecError, one
    line, if malformed."""
    kind, _, rest = text.partition(":")
    if kind in MESSAGE_FAULTS:
        return parse_message_fault(text)
    if kind not in PROCESS_FAULTS:
        raise FaultSpecError(f"fault {text!r}: unknown kind {kind!r} (supported: kill:AGENT:HOUR[:DAY], "
                             "restart:AGENT:HOUR[:DAY], drop|duplicate|corrupt:PATTERN:P, delay:PATTERN:SECONDS[:P])")
    agent, _, when = rest.partition(":")
    hour, _, day = when.partition(":")
    if not agent or not hour.isdigit() or not 1 <= int(hour) <= HOURS or not (day == "" or day.isdigit() and
                                                                              int(day) >= 1):
        raise FaultSpecError(f"fault {text!r}: expected {kind}:AGENT:HOUR[:DAY] with HOUR in 1..{HOURS} and DAY >= 1")
    return Fault(agent, int(hour), kind, int(day or 1))
