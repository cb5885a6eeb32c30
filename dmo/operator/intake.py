"""What the DMO does with one valid message from an agent, decided on its state alone: bound to this run, an exact
copy of a message taken before, admitted (day, sender, process, sequence number), a rejoin, a realised day (taken in
any phase once its day is operated, and never read by clearing or settlement), or the phase's to take.

Pure but for the state it updates, so the DMO's machine (``machine.py``) and the tests drive the same decisions; it
then journals, receipts, publishes and logs what the outcome says.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from messages import GridState, MeterReport, Registration, Schedule
from messages.schemas import AgentDay

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


def receive(state: DayState, msg, sha256: str, accept: Accept, network=None, placement=None) -> Outcome:
    """Decide on ``msg``, whose payload hashes to ``sha256``, and update ``state`` accordingly. ``network`` and
    ``placement`` (agent -> bus) are the run's feeder, if any, which a rejoin's bus is checked on as a first
    registration's is (``registration``)."""
    refusal = acceptance.check_run(msg, state.run_token)
    if refusal:
        return Outcome(REFUSED, refusal)
    state.guard.heard(msg.sender, msg.incarnation)
    if state.guard.again(msg.sender, msg.incarnation, msg.seq, sha256):
        state.again += 1
        return Outcome(AGAIN)
    rejoining = isinstance(msg, Registration) and msg.sender in state.registered
    of_the_run = rejoining or isinstance(msg, AgentDay)  # a rejoin, or a realised day that came after midnight
    refusal = ((None if of_the_run else acceptance.check_day(msg, state.market_day))
               or acceptance.check_registered(msg, state.registered)
               or state.guard.check(msg.sender, msg.incarnation, msg.seq, isinstance(msg, Registration)))
    what = ACCEPTED
    if refusal is None:
        if rejoining:
            refusal = rejoin.rejoin_refusal(state, msg, network, placement)
            if refusal is None:
                rejoin.readmit(state, msg)
                what = REJOINED
        elif isinstance(msg, AgentDay):
            refusal = realised_day(state, msg)
        elif isinstance(msg, Schedule) and msg.sender in state.rescheduling:
            state.schedules[msg.sender] = msg  # a rejoined agent's new schedule replaces the old one
            state.rescheduling.discard(msg.sender)
        else:
            refusal = accept(msg)
    if refusal is not None:
        return Outcome(REFUSED, refusal)
    state.count_accepted(msg, sha256)
    return Outcome(what)


def realised_day(state: DayState, msg: AgentDay) -> Refusal | None:
    """An agent's realised day is taken whatever the phase (``acceptance.check_agent_day``): its market day goes into
    ``state.realised``; the DMO keeps the day itself for the run's result (finished.py)."""
    taken = state.realised.setdefault(msg.sender, set())
    refusal = acceptance.check_agent_day(msg, state.market_day, state.first_market_day, state.phase, state.hour, taken)
    if refusal is None:
        taken.add(msg.market_day)
    return refusal


# --- each phase's rule (``Accept``), on the state alone ----------------------------------------------------------

def registration(state: DayState, network=None, placement=None) -> Accept:
    """While registration is open: a registration registers its agent, at its bus on a feeder (``network`` and the
    run's ``placement``, ``acceptance.check_bus``); anything else is out of phase."""

    def accept(msg):
        if not isinstance(msg, Registration):
            return acceptance.out_of_phase(msg, state.phase)
        refusal = acceptance.check_bus(msg, network, placement or {})
        if refusal is not None:
            return refusal
        state.registered[msg.sender] = msg
        state.meter[msg.sender] = {}
        return None

    return accept


def first_of_each(state: DayState, store: dict) -> Accept:
    """The first message of each agent of the kind the phase waits for (``acceptance.DUE``: its bid, its schedule)
    goes into ``store``; a second is a repeat, another kind out of phase."""
    kind = acceptance.DUE[state.phase]

    def accept(msg):
        if msg.kind != kind:
            return acceptance.out_of_phase(msg, state.phase)
        if msg.sender in store:
            return acceptance.repeated(kind, msg.sender)
        store[msg.sender] = msg
        return None

    return accept


def meter_report(state: DayState, hour: int, subperiods: int, grid: GridState) -> Accept:
    """In real-time hour ``hour`` (1..24), whose grid state is ``grid``: the hour's meter report of each agent
    (``acceptance.check_meter_report``) goes into ``state.meter``."""

    def accept(msg):
        if not isinstance(msg, MeterReport):
            return acceptance.out_of_phase(msg, state.phase)
        refusal = acceptance.check_meter_report(msg, hour, subperiods, state.meter[msg.sender],
                                                state.registered[msg.sender], grid.connected)
        if refusal:
            return refusal
        state.meter[msg.sender][hour - 1] = msg.p_m_mw
        return None

    return accept


def out_of_phase(state: DayState) -> Accept:
    """When no answer is due (settlement): everything is out of phase."""
    return lambda msg: acceptance.out_of_phase(msg, state.phase)
