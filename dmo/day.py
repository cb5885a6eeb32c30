"""The DMO's market day (SPEC section 6): phases with deadlines, driven over a Bus, ending in settlement.

The DMO reads everything it receives from one queue on its main thread, so the day's state is touched by one
thread only; Zenoh's callback threads just enqueue. Each phase ends when every live registered agent has
answered or its deadline passes; late, duplicate, out-of-phase and foreign messages are rejected with a reason,
published on ``dmo/rejected`` for the recording, counted, and never change an award or a settlement.
"""

from __future__ import annotations

import logging
import queue
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from messages import (DMO, Award, Bid, CallForBids, Clock, DaySummary, GridState, Incident, MeterReport,
                      Registration, Schedule, SettlementStatement, StatementLine)
from messages.codec import MessageError, make_rejection
from messages.schemas import AgentTotals
from messages.transport import Bus

from .clearing import Bid as ClearingBid
from .clearing import ClearingResult, Step, clear, fixed_awards
from .settlement import Statement, settle

log = logging.getLogger("dmosim.dmo")

RULES_VERSION = 1
RULES = ("energy charge = clearing price x award per hour; penalty = c x max(P_M - P_sch, 0) x dt per sub-period; "
         "under-import credited at the credit rate (default 0); a missing sub-period is settled at P_M = the "
         "agent's registered max import with no credit (docs/market.md)")


@dataclass(frozen=True)
class DayConfig:
    """Everything the DMO needs to run one day. Deadlines are wall-clock seconds per phase (per hour in real
    time). ``fixed_awards`` (24 MW) replaces clearing by those awards for every agent (the paper's Table I)."""

    market_day: str
    agents: int
    iso_price: tuple[float, ...]
    import_limit: float
    export_limit: float
    penalty: float
    subperiods: int
    islanded_hours: tuple[int, ...]
    credit: float = 0.0
    fixed_awards: tuple[float, ...] | None = None
    price_floor: float = -1000.0
    price_cap: float = 10_000.0
    registration_s: float = 60.0
    bids_s: float = 600.0
    schedule_s: float = 1800.0
    hour_s: float = 300.0


@dataclass
class DayState:
    """What the DMO has accepted so far; only the DMO's main thread touches it."""

    registered: dict[str, Registration] = field(default_factory=dict)
    gone: set[str] = field(default_factory=set)
    bids: dict[str, Bid] = field(default_factory=dict)
    schedules: dict[str, Schedule] = field(default_factory=dict)
    meter: dict[str, dict[int, tuple[float, ...]]] = field(default_factory=dict)
    incidents: list[Incident] = field(default_factory=list)
    rejected: int = 0
    phase: str = "registration"
    hour: int | None = None

    def live(self) -> list[str]:
        return sorted(a for a in self.registered if a not in self.gone)


@dataclass(frozen=True)
class DayResult:
    clearing: ClearingResult
    statements: dict[str, Statement]
    summary: DaySummary
    state: DayState
    phase_s: dict[str, float]


def island_hours(start: int, hours: int) -> tuple[int, ...]:
    """The hours start..start+hours-1 of one islanding event (none if ``hours`` is 0)."""
    return tuple(range(start, start + hours)) if hours else ()


def draw_islanding(hours: int, seed: int) -> tuple[int, ...]:
    """One islanding event of ``hours`` whole hours at a seeded uniform start, as the scenarios draw them."""
    if not hours:
        return ()
    start = 1 + int(np.random.default_rng([seed, 7]).integers(0, 25 - hours))
    return island_hours(start, hours)


class MarketDay:
    """Runs one day on an open bus. ``on_progress(phase, hour)`` is called as the clock advances."""

    def __init__(self, bus: Bus, config: DayConfig, on_progress: Callable[[str, int | None], None] | None = None):
        self.bus, self.config = bus, config
        self.state = DayState()
        self.events: queue.Queue = queue.Queue()
        self.on_progress = on_progress or (lambda phase, hour: None)
        bus.on_reject = lambda key, payload, err: self.events.put(("reject", key, payload, err))

    # --- plumbing ------------------------------------------------------------------------------------------

    def _listen(self) -> None:
        self.bus.subscribe(f"{self.bus.keys.prefix}/agent/**", lambda k, m, t: self.events.put(("msg", k, m, t)))
        self.bus.watch_presence(lambda name: self.events.put(("join", name)),
                                lambda name: self.events.put(("leave", name)))

    def _publish(self, msg) -> None:
        self.bus.publish(msg)

    def _clock(self, phase: str, deadline_s: float, hour: int | None = None) -> None:
        self.state.phase, self.state.hour = phase, hour
        self.on_progress(phase, hour)
        self._publish(Clock(sender=DMO, market_day=self.config.market_day, phase=phase, hour=hour,
                            deadline_s=deadline_s))

    def _incident(self, agent: str | None, reason: str) -> None:
        s = self.state
        s.incidents.append(Incident(agent=agent, phase=s.phase, hour=s.hour, reason=reason[:500]))
        log.warning("%s%s: %s%s", s.phase, f" hour {s.hour}" if s.hour else "", f"{agent}: " if agent else "", reason)

    def _reject(self, key: str, payload: bytes, err: MessageError, offender: str | None) -> None:
        self.state.rejected += 1
        self._incident(offender, f"rejected message on {key.split('/', 2)[-1]}: {err.reason}")
        self._publish(make_rejection(key, payload, err, market_day=self.config.market_day, offender=offender))

    def _refuse(self, key: str, msg, code: str, reason: str) -> None:
        from messages import encode  # noqa: PLC0415  (only needed for the rare refusal)

        self._reject(key, encode(msg), MessageError(reason, code), msg.sender)

    def _wait(self, deadline: float, waiting_for: Callable[[], list[str]], what: str, accept,
              name_late: bool = True) -> None:
        """Handle events until nobody is ``waiting_for`` or the deadline passes; then name the late agents.

        Halfway to the deadline the DMO logs who it is waiting for, so a stall is never silent.
        """
        warned = False
        start = time.monotonic()
        while waiting_for():
            now = time.monotonic()
            if now >= deadline:
                for agent in waiting_for() if name_late else ():
                    self._incident(agent, f"late: no {what} by the deadline")
                return
            if not warned and now >= start + (deadline - start) / 2:
                log.warning("%s: still waiting for %s from %s", self.state.phase, what, ", ".join(waiting_for()))
                warned = True
            try:
                event = self.events.get(timeout=min(deadline - now, max(0.05, (deadline - start) / 2 - (now - start))))
            except queue.Empty:
                continue
            self._handle(event, accept)

    def _handle(self, event, accept) -> None:
        kind = event[0]
        if kind == "reject":
            _, key, payload, err = event
            self._reject(key, payload, err, _offender(key))
        elif kind == "join":
            if event[1] in self.state.gone and event[1] in self.state.registered:
                self._incident(event[1], "reappeared after vanishing")
                self.state.gone.discard(event[1])
        elif kind == "leave":
            name = event[1]
            if name in self.state.registered and name not in self.state.gone:
                self.state.gone.add(name)
                self._incident(name, "vanished (liveliness lost); settled by the missing-data rule")
        else:
            _, key, msg, _ = event
            reason = self._check(msg)
            if reason:
                self._refuse(key, msg, *reason)
            else:
                accept(key, msg)

    def _check(self, msg) -> tuple[str, str] | None:
        if msg.market_day != self.config.market_day:
            return "wrong_day", f"market day {msg.market_day}, expected {self.config.market_day}"
        if not isinstance(msg, Registration) and msg.sender not in self.state.registered:
            return "unregistered", f"{msg.sender} is not registered"
        return None

    def _out_of_phase(self, key, msg) -> None:
        code = "late" if _PHASE_OF.get(msg.kind, 99) < _ORDER[self.state.phase] else "invalid"
        self._refuse(key, msg, code, f"{msg.kind} is out of phase (now {self.state.phase})")

    # --- phases --------------------------------------------------------------------------------------------

    def run(self, before_start: Callable[[], None] | None = None) -> DayResult:
        """Run the day. ``before_start`` is called once the DMO listens and before its first message (to wait
        for a recorder, so that the recording misses nothing)."""
        self._listen()
        if before_start is not None:
            before_start()
        timings = {}
        for phase, step in (("registration", self._registration), ("bidding", self._bidding),
                            ("clearing", self._clearing), ("scheduling", self._scheduling),
                            ("realtime", self._realtime), ("settlement", self._settlement)):
            start = time.monotonic()
            out = step()
            timings[phase] = time.monotonic() - start
        statements, summary, clearing = out
        return DayResult(clearing, statements, summary, self.state, timings)

    def _registration(self):
        s, c = self.state, self.config
        self._clock("registration", c.registration_s)

        def accept(key, msg):
            if isinstance(msg, Registration) and msg.sender not in s.registered:
                s.registered[msg.sender] = msg
                s.meter[msg.sender] = {}
                log.info("registered %s (%d/%d)", msg.sender, len(s.registered), c.agents)
            elif isinstance(msg, Registration):
                self._refuse(key, msg, "duplicate", f"{msg.sender} is already registered")
            else:
                self._out_of_phase(key, msg)

        missing = lambda: [f"{c.agents - len(s.registered)} more agent(s)"] if len(s.registered) < c.agents else []
        self._wait(time.monotonic() + c.registration_s, missing, "registration", accept, name_late=False)
        if len(s.registered) < c.agents:
            self._incident(None, f"only {len(s.registered)} of {c.agents} agents registered by the deadline")
        if not s.registered:
            raise RuntimeError("no agent registered before the registration deadline")

    def _bidding(self):
        s, c = self.state, self.config
        self._clock("bidding", c.bids_s)
        self._publish(CallForBids(sender=DMO, market_day=c.market_day, iso_price_per_mwh=c.iso_price,
                                  price_floor_per_mwh=c.price_floor, price_cap_per_mwh=c.price_cap,
                                  import_limit_mw=c.import_limit, export_limit_mw=c.export_limit,
                                  penalty_per_mwh=c.penalty, credit_per_mwh=c.credit, subperiods=c.subperiods,
                                  deadline_s=c.bids_s))

        def accept(key, msg):
            if isinstance(msg, Bid) and msg.sender in s.bids:
                self._refuse(key, msg, "duplicate", f"second bid from {msg.sender}; the first one stands")
            elif isinstance(msg, Bid):
                s.bids[msg.sender] = msg
            else:
                self._out_of_phase(key, msg)

        self._wait(time.monotonic() + c.bids_s, lambda: [a for a in s.live() if a not in s.bids], "bid", accept)

    def _clearing(self):
        s, c = self.state, self.config
        self._clock("clearing", c.bids_s)
        agents = sorted(s.registered)
        if c.fixed_awards is not None:
            self.clearing = fixed_awards({a: c.fixed_awards for a in agents}, c.iso_price)
        else:
            bids = [ClearingBid(a, tuple(tuple(Step(st.price_per_mwh, st.quantity_mw) for st in hour)
                                         for hour in s.bids[a].hours)) for a in sorted(s.bids)]
            self.clearing = clear(bids, c.iso_price, c.import_limit, c.export_limit, agents=agents)
        for agent in agents:
            self._publish(Award(sender=DMO, market_day=c.market_day, agent=agent,
                                p_sch_mw=self.clearing.awards[agent], clearing_price_per_mwh=self.clearing.price,
                                penalty_per_mwh=c.penalty, credit_per_mwh=c.credit, subperiods=c.subperiods,
                                rules_version=RULES_VERSION, rules=RULES))

    def _scheduling(self):
        s, c = self.state, self.config
        self._clock("scheduling", c.schedule_s)

        def accept(key, msg):
            if isinstance(msg, Schedule) and msg.sender in s.schedules:
                self._refuse(key, msg, "duplicate", f"second schedule from {msg.sender}")
            elif isinstance(msg, Schedule):
                s.schedules[msg.sender] = msg
            else:
                self._out_of_phase(key, msg)

        self._wait(time.monotonic() + c.schedule_s, lambda: [a for a in s.live() if a not in s.schedules],
                   "schedule", accept)

    def _realtime(self):
        s, c = self.state, self.config
        for hour in range(1, 25):
            self._clock("realtime", c.hour_s, hour)
            connected = hour not in c.islanded_hours
            self._publish(GridState(sender=DMO, market_day=c.market_day, hour=hour, subperiods=c.subperiods,
                                    connected=(connected,) * c.subperiods))

            def accept(key, msg, hour=hour):
                if not isinstance(msg, MeterReport):
                    return self._out_of_phase(key, msg)
                if msg.subperiods != c.subperiods:
                    return self._refuse(key, msg, "invalid", f"{msg.subperiods} sub-periods, the day has {c.subperiods}")
                if msg.hour != hour:
                    code = "late" if msg.hour < hour else "invalid"
                    return self._refuse(key, msg, code, f"meter report for hour {msg.hour} during hour {hour}")
                if (hour - 1) in s.meter[msg.sender]:
                    return self._refuse(key, msg, "duplicate", f"second meter report for hour {hour}")
                cap = s.registered[msg.sender].max_import_mw
                if max(msg.p_m_mw) > cap + 1e-9:
                    return self._refuse(key, msg, "invalid", f"P_M {max(msg.p_m_mw)} MW above registered max {cap}")
                s.meter[msg.sender][hour - 1] = msg.p_m_mw

            self._wait(time.monotonic() + c.hour_s, lambda: [a for a in s.live() if (hour - 1) not in s.meter[a]],
                       f"meter report for hour {hour}", accept)
        return None

    def _settlement(self):
        s, c = self.state, self.config
        self._clock("settlement", c.hour_s)
        while not self.events.empty():  # what arrived since the last hour closed is late, and recorded as such
            self._handle(self.events.get_nowait(), lambda key, msg: self._out_of_phase(key, msg))
        statements, summary = settle(self.clearing.awards, self.clearing.price, s.meter, subperiods=c.subperiods,
                                     penalty=c.penalty, credit=c.credit,
                                     p_m_max={a: r.max_import_mw for a, r in s.registered.items()})
        for agent, st in statements.items():
            self._publish(statement_message(st, c))
        self._publish(DaySummary(
            sender=DMO, market_day=c.market_day, agents=tuple(sorted(s.registered)),
            clearing_price_per_mwh=self.clearing.price,
            totals={a: AgentTotals(energy_charge=float(st.energy_charge), deviation_penalty=float(st.deviation_penalty),
                                   deviation_credit=float(st.credit), total=float(st.total))
                    for a, st in statements.items()},
            rejected_messages=s.rejected, incidents=tuple(s.incidents)))
        return statements, summary, self.clearing


_ORDER = {"registration": 0, "bidding": 1, "clearing": 2, "scheduling": 3, "realtime": 4, "settlement": 5}
_PHASE_OF = {"registration": 0, "bid": 1, "schedule": 3, "meter_report": 4}


def _offender(key: str) -> str | None:
    parts = key.split("/")
    return parts[3] if len(parts) > 3 and parts[2] == "agent" else None


def statement_message(st: Statement, c: DayConfig) -> SettlementStatement:
    """A settlement Statement as the message the DMO publishes (hours 1..24 on the wire)."""
    lines = tuple(StatementLine(hour=line.hour + 1, p_sch_mw=line.award_mwh, clearing_price_per_mwh=line.price,
                                energy_charge=float(line.energy_charge), import_mwh=line.import_mwh,
                                deviation_mwh=line.deviation_mwh, under_import_mwh=line.under_import_mwh,
                                deviation_penalty=float(line.penalty), deviation_credit=float(line.credit),
                                total=float(line.total), missing=line.missing,
                                missing_subperiods=line.missing_subperiods) for line in st.lines)
    return SettlementStatement(sender=DMO, market_day=c.market_day, agent=st.agent, penalty_per_mwh=c.penalty,
                               credit_per_mwh=c.credit, rules_version=RULES_VERSION, lines=lines,
                               energy_charge=float(st.energy_charge), deviation_penalty=float(st.deviation_penalty),
                               deviation_credit=float(st.credit), total=float(st.total),
                               missing_subperiods=st.missing_subperiods)
