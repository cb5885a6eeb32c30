"""What the DMO does with one valid message from an agent, decided on its state alone: bound to this run, an exact
copy of a message taken before, admitted (day, sender, process, sequence number), a rejoin, or the phase's to take.

Pure but for the state it updates, so the live DMO (``day.py``) and the tests drive the same decisions; the DMO
then journals, receipts, publishes and logs what the outcome says.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from messages import Registration, Schedule

from ..market import acceptance
from ..market.acceptance import Refusal
from . import rejoin
from .state import DayState

ACCEPTED, AGAIN, REFUSED, REJOINED = "accepted", "again", "refused", "rejoined"

Accept = Callable[[object], Refusal | None]  # the phase's rule: takes the message into the state, or refuses it


@dataclass(frozen=True)
class Outcome:
    """``what`` is ACCEPTED, AGAIN (an exact copy of an accepted message: nothing more happens), REFUSED (with
    ``refusal``) or REJOINED (a restarted agent's registration, accepted)."""

    what: str
    refusal: Refusal | None = None

    @property
    def taken(self) -> bool:
        """Whether the message was taken now (and so is journaled): accepted, or a rejoin."""
        return self.what in (ACCEPTED, REJOINED)


def receive(state: DayState, msg, sha256: str, accept: Accept) -> Outcome:
    """Decide on ``msg``, whose payload hashes to ``sha256``, and update ``state`` accordingly."""
    refusal = acceptance.check_run(msg, state.run_token)
    if refusal:
        return Outcome(REFUSED, refusal)
    state.guard.heard(msg.sender, msg.incarnation)
    if state.guard.again(msg.sender, msg.incarnation, msg.seq, sha256):
        state.again += 1
        return Outcome(AGAIN)
    refusal = (acceptance.check_day(msg, state.market_day) or acceptance.check_registered(msg, state.registered)
               or state.guard.check(msg.sender, msg.incarnation, msg.seq, isinstance(msg, Registration)))
    what = ACCEPTED
    if refusal is None:
        if isinstance(msg, Registration) and msg.sender in state.registered:
            refusal = rejoin.rejoin_refusal(state, msg)
            if refusal is None:
                rejoin.readmit(state, msg)
                what = REJOINED
        elif isinstance(msg, Schedule) and msg.sender in state.rescheduling:
            state.schedules[msg.sender] = msg  # a rejoined agent's new schedule replaces the old one
            state.rescheduling.discard(msg.sender)
        else:
            refusal = accept(msg)
    if refusal is not None:
        return Outcome(REFUSED, refusal)
    state.count_accepted(msg, sha256)
    return Outcome(what)
