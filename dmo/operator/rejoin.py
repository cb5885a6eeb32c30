"""Agents that come back: one that vanished (liveliness lost) and reappears, reconnected or restarted, is sent
again what it needs to go on; one restarted (a later incarnation of it registers) rejoins the run, if nothing about
it changed, whatever the DMO saw of its presence and whichever phase the day is in.

Pure decisions on the DMO's state; its machine (machine.py) publishes what they name. Agents take what they already have as
a no-op, so a message sent again harms no one. Hours an agent does not report are settled by the missing-data
rule (docs/market.md).
"""

from __future__ import annotations

from messages import Registration

from ..market.acceptance import Refusal, bus_at, check_bus, repeated
from .state import DayState

CALL_FOR_BIDS, AWARD, GRID_STATE = "call_for_bids", "award", "grid_state"


def rejoin_refusal(state: DayState, msg: Registration, network=None, placement=None) -> Refusal | None:
    """Whether a registered agent's new registration is refused: from the process already admitted it is a repeat;
    from a later one (a restart) it must name the same case and limits as at first and, on a feeder (``network``
    and the run's ``placement``), pass the bus rule of a first registration (``acceptance.check_bus``) at the bus
    it was registered at."""
    agent = msg.sender
    if msg.incarnation == state.guard.incarnation.get(agent):
        return repeated("registration", agent)
    first = state.registered[agent]
    if (msg.case, msg.max_import_mw, msg.max_export_mw) != (first.case, first.max_import_mw, first.max_export_mw):
        return "invalid", (f"{agent} cannot rejoin: it registered again with another case or other limits than "
                           "at first")
    placement = placement or {}
    refusal = check_bus(msg, network, placement)
    if refusal is not None:
        return refusal[0], f"{agent} cannot rejoin: {refusal[1]}"
    if bus_at(msg, placement) != bus_at(first, placement):
        return "invalid", (f"{agent} cannot rejoin: it names bus {bus_at(msg, placement)}, but registered at bus "
                           f"{bus_at(first, placement)} at first")
    return None


def readmit(state: DayState, msg: Registration) -> None:
    """Take a restarted agent back: live, its new process admitted (numbering its messages from 0), and (once
    awards are out, before settlement) owing a new schedule, which is accepted even though it sent one before."""
    agent = msg.sender
    state.vanished.pop(agent, None)
    state.gone.discard(agent)
    state.guard.admit(agent, msg.incarnation)
    if state.phase in ("scheduling", "realtime"):
        state.rescheduling.add(agent)


def resend_plan(state: DayState, agent: str, cleared: bool, grid_known: bool) -> tuple[tuple[str, ...], str]:
    """What to send an agent that comes back (kinds among CALL_FOR_BIDS, AWARD, GRID_STATE), and what to say of
    it in the incident. ``cleared``: awards exist; ``grid_known``: this hour's grid state was published."""
    phase = state.phase
    if phase == "bidding":
        if agent in state.bids:
            return (), "nothing: its bid stands"
        return (CALL_FOR_BIDS,), "the call for bids again"
    if phase in ("scheduling", "realtime") and cleared:
        if phase == "realtime" and grid_known:
            if state.hour - 1 in state.meter.get(agent, {}):  # an earlier process reported it: the next hour
                return (AWARD,), f"its award again (hour {state.hour} is reported)"
            return (AWARD, GRID_STATE), f"its award and the grid state of hour {state.hour} again"
        return (AWARD,), "its award again"
    return (), "nothing: registration is open" if phase == "registration" else "nothing"
