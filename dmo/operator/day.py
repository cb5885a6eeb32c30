"""The DMO's market day: its phases in order, each with a deadline, driven over a Bus and ending in settlement
(docs/protocol.md).

The DMO reads everything it receives from one queue on its main thread, so the day's state is touched by one
thread only; Zenoh's callback threads just enqueue. Each phase ends when every live registered agent has
answered or its deadline passes. What the day accepts is decided by the market's rules (market/acceptance.py)
and the replay guard (guard.py); what it publishes is built by outbox.py; the journal (journal.py) lets a
restarted DMO resume the day, and rejoin.py decides what an agent that comes back is sent again. A refused
message is published on ``dmo/rejected`` with its reason, counted, and never changes an award or a settlement.
"""

from __future__ import annotations

import logging
import queue
import time
from dataclasses import dataclass
from typing import Callable

from messages import PHASES, Bid, GridState, MeterReport, Registration, Schedule, encode, make_rejection
from messages.codec import MessageError
from messages.transport import Bus
from scenarios.horizon import HOURS
from scenarios.names import check_agent_id

from ..market import acceptance
from ..market.acceptance import PHASE_ORDER, Refusal
from ..market.clearing import BidCurve, ClearingResult, Step, clear, fixed_awards
from ..market.settlement import DayTotals, Statement, settle
from . import outbox, rejoin
from .config import DayConfig
from .history import DayHistory
from .journal import Journal, restore, traffic
from .state import DayState

log = logging.getLogger("dmosim.dmo")

@dataclass(frozen=True)
class DayResult:
    clearing: ClearingResult
    statements: dict[str, Statement]
    totals: DayTotals
    state: DayState
    phase_s: dict[str, float]

    def report(self, run_id: str, config: DayConfig, transport: dict) -> dict:
        """The ``dmosim run --json`` object (README, "Commands"), from the DMO's view of the day."""
        s = self.state
        return {
            "run_id": run_id, "market_day": config.market_day, "agents": sorted(s.registered),
            "islanded_hours": list(config.islanded_hours),
            "clearing_prices": list(self.clearing.price), "congestion": list(self.clearing.congested),
            "awards": {a: list(v) for a, v in self.clearing.awards.items()},
            "settlement": {a: {"energy_charge": float(st.energy_charge),
                               "deviation_penalty": float(st.deviation_penalty),
                               "credit": float(st.credit), "total": float(st.total),
                               "award_mwh": sum(line.award_mwh for line in st.lines),
                               "import_mwh": sum(line.import_mwh for line in st.lines),
                               "deviation_mwh": sum(line.deviation_mwh for line in st.lines),
                               "missing_subperiods": st.missing_subperiods}
                           for a, st in self.statements.items()},
            "day_summary": self.totals.as_dict(),
            "expected_cost": {a: m.expected_cost for a, m in s.schedules.items()},
            "rejected_messages": s.rejected, "rejected_by_code": dict(s.rejected_by_code),
            "accepted_messages": dict(s.accepted), "transport": transport,
            "incidents": [i.model_dump() for i in s.incidents],
            "phase_s": self.phase_s,
        }


def bid_curve(bid: Bid) -> BidCurve:
    """A received bid as the clearing reads it (hours 0..23)."""
    return BidCurve(bid.sender, tuple(tuple(Step(st.price_per_mwh, st.quantity_mw) for st in hour)
                                      for hour in bid.hours))


class MarketDay:
    """Runs one day on an open bus. ``on_progress(phase, hour)`` is called as the clock advances."""

    def __init__(self, bus: Bus, config: DayConfig, on_progress: Callable[[str, int | None], None] | None = None):
        self.bus, self.config = bus, config
        self.state = DayState()
        self.events: queue.Queue = queue.Queue()
        self.on_progress = on_progress or (lambda phase, hour: None)
        self.clearing: ClearingResult | None = None
        self._grid: GridState | None = None  # the current hour's, re-sent to an agent that rejoins
        self._bids_due = 0.0
        self.journal: Journal | None = None
        self.history = DayHistory()
        self._resumed: tuple[str, int | None] | None = None
        bus.on_reject = lambda key, payload, err: self.events.put(("reject", key, payload, err))
        bus.tap = self._traffic

    # --- the phases --------------------------------------------------------------------------------------------

    def run(self, before_start: Callable[[], None] | None = None) -> DayResult:
        """Run the day. ``before_start`` is called once the DMO listens and before its first message (to wait
        for a recorder, so that the recording misses nothing)."""
        if self.config.journal:
            self.journal = Journal(self.config.journal, self.bus.keys.run_id, self.config.market_day)
            self._resumed = restore(self.state, self.journal.entries)
            self.history = DayHistory(traffic(self.journal.entries))
            if self._resumed is not None:
                log.warning("resuming the day from %s: %s, %d accepted messages", self.journal.path,
                            _when(*self._resumed), sum(self.state.accepted.values()))
        self._listen()
        if before_start is not None:
            before_start()
        steps = dict(zip(PHASES, (self._registration, self._bidding, self._clearing, self._scheduling,
                                  self._realtime, self._settlement)))
        first = 0
        if self._resumed is not None:
            first = PHASE_ORDER[self._resumed[0]]
            self._await_agents()
            if first > PHASE_ORDER["clearing"]:
                self._clear()
                if first == PHASE_ORDER["scheduling"]:  # some awards may not have gone out; agents ignore a repeat
                    self._publish_awards()
        timings = {}
        for phase in PHASES[first:]:
            start = time.monotonic()
            out = steps[phase]()
            timings[phase] = time.monotonic() - start
        statements, totals = out
        self._linger()
        if self.journal is not None:
            self.journal.close()
        return DayResult(self.clearing, statements, totals, self.state, timings)

    def _registration(self) -> None:
        s, c = self.state, self.config
        self._clock("registration", c.registration_s)

        def accept(key, msg):
            if not isinstance(msg, Registration):
                return self._refuse(key, msg, acceptance.out_of_phase(msg, s.phase))
            if msg.sender in s.registered:
                return self._refuse(key, msg, acceptance.repeated("registration", msg.sender))
            s.registered[msg.sender] = msg
            s.meter[msg.sender] = {}
            log.info("registered %s (%d/%d)", msg.sender, len(s.registered), c.agents)

        missing = lambda: [f"{c.agents - len(s.registered)} more agent(s)"] if len(s.registered) < c.agents else []
        self._wait(time.monotonic() + c.registration_s, missing, "registration", accept, name_late=False)
        if len(s.registered) < c.agents:
            self._incident(None, f"only {len(s.registered)} of {c.agents} agents registered by the deadline")
        if not s.registered:
            raise RuntimeError("no agent registered before the registration deadline")

    def _bidding(self) -> None:
        s, c = self.state, self.config
        self._clock("bidding", c.bids_s)
        self._bids_due = time.monotonic() + c.bids_s
        self._publish(outbox.call_for_bids(c, c.bids_s))
        self._wait(self._bids_due, lambda: [a for a in s.live() if a not in s.bids], "bid",
                   self._first_of_each(Bid, s.bids, "bid"))

    def _clearing(self) -> None:
        self._clock("clearing", self.config.bids_s)
        self._clear()
        self._publish_awards()

    def _clear(self) -> None:
        """Clear the accepted bids (a pure function of them: a resumed DMO gets the same awards again)."""
        s, c = self.state, self.config
        agents = sorted(s.registered)
        if c.fixed_awards is not None:
            self.clearing = fixed_awards({a: c.fixed_awards for a in agents}, c.iso_price)
        else:
            bids = [bid_curve(s.bids[a]) for a in sorted(s.bids)]
            self.clearing = clear(bids, c.iso_price, c.import_limit, c.export_limit, agents=agents)

    def _publish_awards(self) -> None:
        for agent in sorted(self.state.registered):
            self._publish(outbox.award(self.config, self.clearing, agent))

    def _scheduling(self) -> None:
        s, c = self.state, self.config
        self._clock("scheduling", c.schedule_s)
        self._wait(time.monotonic() + c.schedule_s, lambda: [a for a in s.live() if a not in s.schedules],
                   "schedule", self._first_of_each(Schedule, s.schedules, "schedule"))

    def _realtime(self) -> None:
        s, c = self.state, self.config
        first = self._resumed[1] if self._resumed and self._resumed[0] == "realtime" else 1
        for hour in range(first, HOURS + 1):
            self._clock("realtime", c.hour_s, hour)
            self._grid = outbox.grid_state(c, hour)
            self._publish(self._grid)

            def accept(key, msg, hour=hour):
                if not isinstance(msg, MeterReport):
                    return self._refuse(key, msg, acceptance.out_of_phase(msg, s.phase))
                refusal = acceptance.check_meter_report(msg, hour, c.subperiods, s.meter[msg.sender],
                                                        s.registered[msg.sender].max_import_mw)
                if refusal:
                    return self._refuse(key, msg, refusal)
                s.meter[msg.sender][hour - 1] = msg.p_m_mw

            self._wait(time.monotonic() + c.hour_s, lambda: [a for a in s.live() if (hour - 1) not in s.meter[a]],
                       f"meter report for hour {hour}", accept)

    def _settlement(self) -> tuple[dict[str, Statement], DayTotals]:
        s, c = self.state, self.config
        self._clock("settlement", c.hour_s)
        while not self.events.empty():  # what arrived since the last hour closed is late, and recorded as such
            self._handle(self.events.get_nowait(),
                         lambda key, msg: self._refuse(key, msg, acceptance.out_of_phase(msg, s.phase)))
        for incident in s.log.close(s.phase, s.hour):
            log.warning("settlement: %s", incident.reason)
        statements, totals = settle(self.clearing.awards, self.clearing.price, s.meter, subperiods=c.subperiods,
                                    penalty=c.penalty, credit=c.credit,
                                    p_m_max={a: r.max_import_mw for a, r in s.registered.items()})
        for st in statements.values():
            self._publish(outbox.statement_message(st, c.market_day, c.penalty, c.credit))
        self._publish(outbox.day_summary(c.market_day, s.registered, self.clearing.price, statements, s.rejected,
                                         s.incidents))
        return statements, totals

    def _first_of_each(self, kind, store: dict, what: str):
        """Accept the first ``kind`` message of each agent into ``store``; refuse repeats and other kinds."""

        def accept(key, msg):
            if not isinstance(msg, kind):
                self._refuse(key, msg, acceptance.out_of_phase(msg, self.state.phase))
            elif msg.sender in store:
                self._refuse(key, msg, acceptance.repeated(what, msg.sender))
            else:
                store[msg.sender] = msg

        return accept

    # --- a restarted DMO, and agents that come and go ---------------------------------------------------------

    def _await_agents(self) -> None:
        """A resumed DMO waits (at most ``resume_wait_s``) for its agents to reconnect before it goes on; those
        that do not are noted gone, as vanished."""
        s, c = self.state, self.config
        deadline = time.monotonic() + c.resume_wait_s
        while True:  # presence by a liveliness query: the event queue is left to the phase
            waiting = set(s.registered) - self.bus.present(timeout_s=1.0)
            if not waiting or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
        for agent in sorted(waiting):
            s.gone.add(agent)
            s.vanished[agent] = (s.phase, s.hour)
        self._incident(None, f"the DMO restarted and resumed the day {_when(*self._resumed)} from its journal "
                             f"({sum(s.accepted.values())} accepted messages recovered)"
                             + (f"; not back: {', '.join(sorted(waiting))}" if waiting else ""))

    def _joined(self, name: str) -> None:
        s = self.state
        if name in s.gone and name in s.registered:
            s.gone.discard(name)
            since = s.vanished.get(name, (s.phase, None))
            self._incident(name, f"reappeared after vanishing {_when(*since)}{_outage(since, s.phase, s.hour)}; "
                                 f"sent {self._resend(name)}")

    def _left(self, name: str) -> None:
        s = self.state
        if name in s.registered and name not in s.gone:
            s.gone.add(name)
            s.vanished[name] = (s.phase, s.hour)
            self._incident(name, "vanished (liveliness lost); what it does not report is settled by the "
                                 "missing-data rule")

    def _rejoin(self, key: str, msg: Registration) -> None:
        """A registered agent registers again: after vanishing (its process restarted), it rejoins the day."""
        refusal = rejoin.rejoin_refusal(self.state, msg)
        if refusal:
            return self._refuse(key, msg, refusal)
        rejoin.readmit(self.state, msg.sender)
        self._incident(msg.sender, f"rejoined after vanishing (registered again); sent {self._resend(msg.sender)}")

    def _resend(self, agent: str) -> str:
        """Send an agent that comes back what it needs to go on; say what was sent."""
        kinds, said = rejoin.resend_plan(self.state, agent, self.clearing is not None, self._grid is not None)
        for kind in kinds:
            if kind == rejoin.CALL_FOR_BIDS:
                self._publish(outbox.call_for_bids(self.config, round(max(0.1, self._bids_due - time.monotonic()), 1)))
            elif kind == rejoin.AWARD:
                self._publish(outbox.award(self.config, self.clearing, agent))
            else:
                self._publish(self._grid)
        return said

    # --- plumbing ---------------------------------------------------------------------------------------------

    def _listen(self) -> None:
        self.bus.subscribe(f"{self.bus.keys.prefix}/agent/**", lambda k, m, t: self.events.put(("msg", k, m, t)))
        self.bus.watch_presence(lambda name: self.events.put(("join", name)),
                                lambda name: self.events.put(("leave", name)))
        self.bus.serve(self.bus.keys.everything(), self.history.answer)

    def _traffic(self, key: str, payload: bytes, at: int) -> None:
        """Every payload sent or received (the bus's tap, on Zenoh's threads too): kept for late joiners."""
        self.history.record(key, payload, at)
        if self.journal is not None:
            self.journal.traffic(key, payload, at)

    def _publish(self, msg) -> None:
        self.bus.publish(msg)

    def _clock(self, phase: str, deadline_s: float, hour: int | None = None) -> None:
        self.state.phase, self.state.hour = phase, hour
        if self.journal is not None:
            self.journal.clock(phase, hour)
        self.on_progress(phase, hour)
        self._publish(outbox.clock(self.config, phase, hour, deadline_s))

    def _incident(self, agent: str | None, reason: str) -> None:
        s = self.state
        incident = s.log.add(agent, s.phase, s.hour, reason)
        if self.journal is not None:
            self.journal.incident(incident)
        log.warning("%s%s: %s%s", s.phase, f" hour {s.hour}" if s.hour else "", f"{agent}: " if agent else "",
                    incident.reason)

    def _reject(self, key: str, payload: bytes, err: MessageError, offender: str | None) -> None:
        listed = self.state.log.count_rejection(err.code)
        if self.journal is not None:
            self.journal.rejected(err.code)
        if listed:
            self._incident(offender, f"rejected message on {key.split('/', 2)[-1]}: {err.code}: {err.reason}")
        else:
            log.info("rejected message on %s: %s: %s", key, err.code, err.reason)
        self._publish(make_rejection(key, payload, err, market_day=self.config.market_day, offender=offender))

    def _refuse(self, key: str, msg, refusal: Refusal) -> None:
        code, reason = refusal
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
            self._joined(event[1])
        elif kind == "leave":
            self._left(event[1])
        else:
            self._received(event[1], event[2], accept)

    def _received(self, key: str, msg, accept) -> None:
        """A valid message from an agent: admitted (its day, its sender, its sequence number), then handled."""
        s = self.state
        refusal = self._admission(msg)
        if refusal:
            return self._refuse(key, msg, refusal)
        before = s.rejected
        if isinstance(msg, Registration) and msg.sender in s.registered:
            self._rejoin(key, msg)
        elif isinstance(msg, Schedule) and msg.sender in s.rescheduling:
            s.schedules[msg.sender] = msg
            s.rescheduling.discard(msg.sender)
            log.info("%s rescheduled after rejoining", msg.sender)
        else:
            accept(key, msg)
        if s.rejected == before:
            s.count_accepted(msg)
            if self.journal is not None:
                self.journal.accepted(key, msg)

    def _admission(self, msg) -> Refusal | None:
        s = self.state
        refusal = acceptance.check_day(msg, self.config.market_day) or acceptance.check_registered(msg, s.registered)
        if refusal:
            return refusal
        # A restarted agent numbers its messages from 0 again: its re-registration after vanishing is let through.
        if isinstance(msg, Registration) and msg.sender in s.vanished:
            return None
        return s.guard.check(msg.sender, msg.seq)

    def _linger(self) -> None:
        """Stay until the live agents have left (they leave once they have the summary), at most ``linger_s``:
        the DMO is the agents' router, and closing at once could cut off the summary still on its way."""
        waiting = set(self.state.live())
        deadline = time.monotonic() + self.config.linger_s
        while waiting and (left := deadline - time.monotonic()) > 0:
            try:
                event = self.events.get(timeout=left)
            except queue.Empty:
                break
            if event[0] == "leave":
                waiting.discard(event[1])


def _when(phase: str, hour: int | None) -> str:
    return f"in {phase}" + (f" hour {hour}" if hour else "")


def _outage(since: tuple[str, int | None] | None, phase: str, hour: int | None) -> str:
    if since and since[1] and hour and hour > since[1]:
        return f", {hour - since[1]} hour(s) later"
    return ""


def _offender(key: str) -> str | None:
    """The agent a refused payload's key names, if it names one: any text can arrive there, and only a valid
    agent id may go into an incident or a Rejection."""
    parts = key.split("/")
    if len(parts) > 3 and parts[2] == "agent":
        try:
            return check_agent_id(parts[3])
        except ValueError:
            return None
    return None
