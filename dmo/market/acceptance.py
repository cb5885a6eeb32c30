"""Which messages of a market day the DMO accepts: the rules, as pure functions, that the DMO's machine
(``operator/machine.py``) applies, live or replaying a recorded day.

Each function returns None for an acceptable message, or the refusal as ``(code, reason)``: ``code`` one of
``messages.REJECT_CODES``, ``reason`` one line. A refused message is published on ``dmo/rejected`` with both and
never changes an award or a settlement (docs/protocol.md, "Rejections").
"""

from __future__ import annotations

from collections.abc import Container

from messages import PHASES, MeterReport, Registration
from messages.schemas import AgentDay
from scenarios.horizon import HOURS

from .settlement import READING_TOLERANCE_MW

Refusal = tuple[str, str]

PHASE_ORDER = {phase: i for i, phase in enumerate(PHASES)}  # the clock's phases, in the order of the day
# The phase in which each kind an agent sends is due, and so the kind each phase waits for: the one table the DMO
# reads (operator/intake.py). An agent_day is taken when it comes
# (operator/intake.py), never waited for.
ANSWER_PHASE = {"registration": "registration", "bid": "bidding", "schedule": "scheduling", "meter_report": "realtime",
                "agent_day": "realtime"}
DUE = {phase: kind for kind, phase in ANSWER_PHASE.items() if kind != "agent_day"}


def check_run(msg, run_token: str) -> Refusal | None:
    """A message not bound to this run (recorded in another, or older than version 4) is refused."""
    if msg.run != run_token:
        return "wrong_run", (f"{msg.kind} #{msg.seq} from {msg.sender} carries run token {msg.run or 'none'!r}, "
                             "not this run's: sent to another run, or replayed from one")
    return None


def check_day(msg, market_day: str) -> Refusal | None:
    """A message of another market day is refused."""
    if msg.market_day != market_day:
        return "wrong_day", f"market day {msg.market_day}, expected {market_day}"
    return None


def check_registered(msg, registered) -> Refusal | None:
    """Only a registration may come from an agent that is not registered."""
    if not isinstance(msg, Registration) and msg.sender not in registered:
        return "unregistered", f"{msg.sender} is not registered"
    return None


def out_of_phase(msg, phase: str) -> Refusal:
    """The refusal of a message that is not due now: ``late`` if its phase has passed, else ``invalid``."""
    if isinstance(msg, Registration):
        return "late", f"registration is closed (now {phase}): {msg.sender} is not an agent of this day"
    due = ANSWER_PHASE.get(msg.kind)
    code = "late" if due is not None and PHASE_ORDER[due] < PHASE_ORDER[phase] else "invalid"
    return code, f"{msg.kind} is out of phase (now {phase})"


def repeated(what: str, sender: str) -> Refusal:
    """A second answer of one kind from one agent: the first one stands."""
    if what == "registration":
        return "duplicate", f"{sender} is already registered"
    return "duplicate", f"second {what} from {sender}; the first one stands"


def check_bus(msg: Registration, network, placement) -> Refusal | None:
    """On a feeder (``network``, a ``scenarios.network.Network``; None: the copper plate, where every bus is
    refused), a registration's bus must be one of the feeder's buses other than the substation, and the one
    ``placement`` (agent -> bus) places the agent at, if it does; an agent the run does not place must name its bus."""
    if network is None:
        return None if msg.bus is None else ("invalid", f"{msg.sender} names bus {msg.bus}, but this market has no "
                                                        "feeder (a copper plate)")
    placed = placement.get(msg.sender)
    bus = bus_at(msg, placement)
    if bus is None:
        return "invalid", f"{msg.sender} names no bus and the run places it at none: on a feeder, name your bus"
    if placed is not None and bus != placed:
        return "invalid", f"{msg.sender} names bus {bus}, but the run placed it at bus {placed}"
    try:
        network.bus_of(bus, f"registration of {msg.sender}")
    except ValueError as err:
        return "invalid", str(err)
    return None


def bus_at(msg: Registration, placement) -> str | None:
    """The bus a registration puts its agent at: the one it names, else the one ``placement`` places it at."""
    return msg.bus if msg.bus is not None else placement.get(msg.sender)


def check_meter_report(msg: MeterReport, hour: int, subperiods: int, reported, registration: Registration,
                       connected: tuple[bool, ...] | None = None) -> Refusal | None:
    """A meter report is accepted in real-time hour ``hour`` (1..24) if it is for this hour, at the day's
    ``subperiods``, the first for the hour (``reported`` holds the agent's hour indices 0..23 already taken), has
    every reading within the agent's registered limits, -max_export_mw <= P_M <= max_import_mw, and reads 0 in every
    sub-period the hour's grid state ``connected`` says is islanded (U = 0 forces P_M = 0, constraint (18)); each
    within ``READING_TOLERANCE_MW``."""
    if msg.subperiods != subperiods:
        return "invalid", f"{msg.subperiods} sub-periods, the day has {subperiods}"
    if msg.hour != hour:
        return ("late" if msg.hour < hour else "invalid"), f"meter report for hour {msg.hour} during hour {hour}"
    if hour - 1 in reported:
        return "duplicate", f"second meter report for hour {hour}"
    if max(msg.p_m_mw) > registration.max_import_mw + READING_TOLERANCE_MW:
        return "invalid", f"P_M {max(msg.p_m_mw)} MW above registered max import {registration.max_import_mw}"
    if min(msg.p_m_mw) < -registration.max_export_mw - READING_TOLERANCE_MW:
        return "invalid", f"P_M {min(msg.p_m_mw)} MW below registered max export -{registration.max_export_mw}"
    islanded = [k for k, up in enumerate(connected or ()) if not up and abs(msg.p_m_mw[k]) > READING_TOLERANCE_MW]
    if islanded:
        k = islanded[0]
        return "invalid", f"P_M {msg.p_m_mw[k]} MW in sub-period {k + 1}, which is islanded: P_M must be 0"
    return None


def check_agent_day(msg: AgentDay, market_day: str, first_day: str, phase: str, hour: int | None,
                    taken: Container[str]) -> Refusal | None:
    """An agent's realised day is accepted once its day has been operated: during the last real-time hour of the day
    being run (``market_day``) or its settlement, or on a later day of the run (it may arrive after the next day
    began: the run began on ``first_day``); once per agent and day (``taken`` holds the market days of the agent's
    realised days already accepted). It is informational: accepting it changes no award and no settlement."""
    if msg.market_day > market_day or msg.market_day < first_day:
        return "wrong_day", f"agent_day of market day {msg.market_day}, which this run has not operated"
    if msg.market_day == market_day and PHASE_ORDER[phase] < PHASE_ORDER["settlement"] and \
            not (phase == "realtime" and hour == HOURS):
        now = f"{phase} hour {hour}" if hour else phase
        return "invalid", f"agent_day of {market_day} before its last hour (now {now})"
    if msg.market_day in taken:
        return "duplicate", f"second agent_day of {msg.market_day} from {msg.sender}; the first one stands"
    return None
