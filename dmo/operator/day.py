"""The DMO's market day: its phases in order, each with a deadline, driven over a Bus and ending in settlement
(docs/protocol.md).

The DMO reads everything it receives from one queue on its main thread, so the day's state is touched by one thread
only; Zenoh's callback threads just enqueue. Each phase ends when every live registered agent has answered
(accepted, or refused: an agent told no is not waited for) or, on the wall clock, its deadline passes; on the
logical clock a phase has no deadline, so a loaded machine makes a run slower, never different (docs/experiments.md,
"Logical and wall-clock time"). What the day accepts is decided by intake.py, on the market's rules
(market/acceptance.py) and the replay guard (guard.py); what it publishes is built by outbox.py; the journal
(journal.py) lets a restarted DMO resume the day, and rejoin.py decides what an agent that comes back is sent again.
A settled day goes to disk as its report (finished.py), and so does each realised day an agent reports, so that the
DMO does not grow with the days of a run. A refused message is published on ``dmo/rejected`` with its reason,
counted, and never changes an award or a settlement.
"""

from __future__ import annotations

import copy
import logging
import math
import queue
import secrets
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

from messages import PHASES, Bid, GridState, make_receipt, make_rejection, sha256
from messages.budget import SenderBudget
from messages.codec import MessageError
from messages.keys import agent_of
from messages.schemas import AgentDay
from messages.transport import Bus
from messages.transport.heap import return_free_memory
from scenarios.horizon import HOURS
from scenarios.names import RECORDER

from ..market.acceptance import PHASE_ORDER
from ..market.clearing import BidCurve, ClearingResult, Step, clear, fixed_awards
from ..market.distflow import NetworkClearing, clear_network
from ..market.settlement import DayTotals, Statement, accepted_day
from . import feeder, intake, outbox, rejoin
from .config import DayConfig
from .events import Event, Joined, Left, OverBudget, Received, Unreadable
from .finished import FinishedDays
from .history import DayHistory, asks_history
from .journal import Journal, restore
from .state import DayState

log = logging.getLogger("dmosim.dmo")

@dataclass(frozen=True)
class DayResult:
    """One settled market day: its clearing, statements and totals, and the DMO's state as the day closed."""

    day: int
    market_day: str
    islanded_hours: tuple[int, ...]
    clearing: ClearingResult
    statements: dict[str, Statement]
    totals: DayTotals
    state: DayState
    phase_s: dict[str, float]
    locked_out: tuple[str, ...] = ()  # agents whose latest process spoke and was not admitted, as the day closed

    def report(self) -> dict:
        """The day as JSON: prices, awards, each agent's settlement, incidents and counts."""
        s = self.state
        return {
            "day": self.day, "market_day": self.market_day, "islanded_hours": list(self.islanded_hours),
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
            "accepted_messages": dict(s.accepted), "received_again": s.again, "dropped_messages": dict(s.dropped),
            "locked_out": list(self.locked_out),
            "incidents": [i.model_dump() for i in s.incidents],
            "phase_s": self.phase_s,
        }


@dataclass(frozen=True)
class RunResult:
    """Every day of a run, in order, as its report (``DayResult.report``), and the last day's whole result (its
    state and statements). The DMO keeps the days it has settled, and the realised days, on disk as the run goes
    (finished.py): they come back here when the run ends."""

    days: list[dict]
    settlement_rule: str  # the rule every day was settled by, with every parameter
    agents: list[str]  # the agents registered
    # agent -> market day -> its agent_day as reported, without the envelope (finished.py)
    realised: dict[str, dict[str, dict]] = field(default_factory=dict)
    last: DayResult | None = None  # the last day's whole result

    def report(self, run_id: str, transport: dict) -> dict:
        """The DMO's part of the ``dmosim run --json`` object (docs/experiments.md, "The result"). A one-day run
        gives that day's fields at the top; a longer one gives the run's: hourly values concatenated day after day,
        each agent's settlement summed, incidents of every day (each with its market day), and ``islanded_hours``
        per day. ``days`` holds each day's own object either way."""
        days, agents = self.days, self.agents
        out = {"run_id": run_id, "agents": agents, "days": days, "settlement_rule": self.settlement_rule,
               "transport": transport, "realised": self.realised_days(agents)}
        if len(days) == 1:
            return {**out, **days[0], "days": days}
        money = ("energy_charge", "deviation_penalty", "credit", "total")
        settlement = {a: {k: (round(sum(d["settlement"][a][k] for d in days), 2) if k in money
                              else sum(d["settlement"][a][k] for d in days)) for k in days[0]["settlement"][a]}
                      for a in days[0]["settlement"]}
        return {**out, "market_day": days[0]["market_day"], "market_days": [d["market_day"] for d in days],
                "islanded_hours": [d["islanded_hours"] for d in days],
                "clearing_prices": [p for d in days for p in d["clearing_prices"]],
                "congestion": [c for d in days for c in d["congestion"]],
                "awards": {a: [x for d in days for x in d["awards"].get(a, [0.0] * HOURS)] for a in agents},
                "settlement": settlement,
                "rejected_messages": sum(d["rejected_messages"] for d in days),
                "rejected_by_code": dict(sum((Counter(d["rejected_by_code"]) for d in days), Counter())),
                "accepted_messages": dict(sum((Counter(d["accepted_messages"]) for d in days), Counter())),
                "received_again": sum(d["received_again"] for d in days),
                "dropped_messages": dict(sum((Counter(d["dropped_messages"]) for d in days), Counter())),
                "locked_out": sorted({a for d in days for a in d["locked_out"]}),
                "incidents": [{**i, "market_day": d["market_day"]} for d in days for i in d["incidents"]]}


    def realised_days(self, agents: list[str]) -> dict[str, list[dict]]:
        """Agent -> the realised days it reported (its ``agent_day`` messages, as received), in order of the day,
        each with the run's ``day`` and its ``market_day``; an agent that reported none has an empty list."""
        day_of = {d["market_day"]: d["day"] for d in self.days}
        return {a: [{"day": day_of.get(market_day), "market_day": market_day, **reported}
                    for market_day, reported in sorted(self.realised.get(a, {}).items())] for a in agents}


def bid_curve(bid: Bid) -> BidCurve:
    """A received bid as the clearing reads it (hours 0..23)."""
    return BidCurve(bid.sender, tuple(tuple(Step(st.price_per_mwh, st.quantity_mw) for st in hour)
                                      for hour in bid.hours))


def clearing_of(config: DayConfig, state: DayState) -> ClearingResult | NetworkClearing:
    """The day's clearing, a pure function of the bids it accepted (a resumed DMO gets the same awards again): on
    the copper plate, or on the feeder with each agent at its bus."""
    agents = sorted(state.registered)
    if config.fixed_awards is not None:
        return fixed_awards({a: config.fixed_awards for a in agents}, config.iso_price)
    bids = [bid_curve(state.bids[a]) for a in sorted(state.bids)]
    if config.network is not None:
        return clear_network(bids, config.network, feeder.sites(config, state), config.iso_price,
                             config.import_limit, config.export_limit, agents=agents, margin=config.voltage_margin,
                             curve=config.iso_curve)
    return clear(bids, config.iso_price, config.import_limit, config.export_limit, agents=agents,
                 curve=config.iso_curve)


def settlement_of(config: DayConfig, state: DayState, clearing: ClearingResult | NetworkClearing
                  ) -> tuple[dict[str, Statement], DayTotals]:
    """The day's statements, a pure function of its awards and the meter reports it accepted; on a feeder each
    agent's energy at its own bus's prices."""
    own = dict(clearing.agent_price) if isinstance(clearing, NetworkClearing) else None
    return config.rule.settle(accepted_day(clearing.awards, clearing.price, state.meter, subperiods=config.subperiods,
                                           registered=state.registered, agent_prices=own))


class MarketDay:
    """Runs the market days of one run on an open bus: registration once, then each day from the call for bids
    to settlement. ``on_progress(phase, hour)`` is called as the clock advances."""

    def __init__(self, bus: Bus, config: DayConfig, on_progress: Callable[[str, int | None], None] | None = None):
        self.bus, self.config = bus, config
        self.state = DayState(market_day=config.market_day)
        self.events: queue.Queue = queue.Queue()
        self.on_progress = on_progress or (lambda phase, hour: None)
        self.clearing: ClearingResult | None = None
        self._grid: GridState | None = None  # the current hour's, re-sent to an agent that rejoins
        self._bids_due = 0.0
        self.journal: Journal | None = None
        self.history: DayHistory | None = None  # opened by run(), on the journal if there is one
        self.finished: FinishedDays | None = None  # opened by run()
        self._resumed: tuple[str, int | None] | None = None
        self._returning: dict[str, float] = {}  # agent the run restarts -> until when it is waited for (monotonic)
        # (agent, kind, hour) of the answers refused in this phase or hour, and agents over their budget in it: an
        # agent told no does not send it again, so it is not waited for
        self._refused: set[tuple[str, str, int | None]] = set()
        self._over: set[str] = set()
        self.budget = SenderBudget(*config.budget)  # what each agent may send in a phase or hour (messages/budget.py)
        bus.on_reject = lambda key, payload, err: self.events.put(Unreadable(key, payload, err))
        bus.tap = self._traffic
        bus.gate = self._admit

    # --- the days and their phases -----------------------------------------------------------------------------

    def run(self, before_start: Callable[[], None] | None = None) -> RunResult:
        """Run the days. ``before_start`` is called once the DMO listens and before its first message (to wait
        for a recorder, so that the recording misses nothing). A DMO restarted on its journal gives the days it
        had finished from the journal and runs again the phase, or hour, it had reached."""
        s, c = self.state, self.config
        self.finished = FinishedDays()
        closed: list[DayState] = []
        if c.journal:
            self.journal = Journal(c.journal, self.bus.keys.run_id, c.market_day)
            self._resumed, closed = restore(s, self.journal.entries, self.finished.realised)
            if self._resumed is not None:
                log.warning("resuming the run from %s: day %d %s, %d accepted messages", self.journal.path, s.day,
                            _when(*self._resumed), sum(s.accepted.values()))
        if not s.run_token:  # a new run (a resumed one keeps the token its journal holds)
            s.run_token = secrets.token_hex(16)
            if self.journal is not None:
                self.journal.run_token(s.run_token)
        self.bus.run_token = s.run_token
        self.history = DayHistory(self.journal)
        self._listen()
        if before_start is not None:
            before_start()
        while closed:  # the days a resumed DMO had finished: each goes to disk as its report, like any other
            self.finished.day(self._settled_again(closed.pop(0)).report())
        last = None
        for day in range(s.day, c.days + 1):
            if day > s.day:
                self.finished.day(last.report())  # the day before goes to disk before the next day's messages come
                last = None
                return_free_memory()  # what the day's messages took from the C heap goes back to the OS
                s.start_day(day, c.market_day_of(day))
            last = self._run_day(day)
        self._linger()
        if last is not None:  # the last day's report after lingering: it counts the realised days accepted meanwhile
            self.finished.day(last.report())
        if self.journal is not None:
            self.journal.close()
        days, realised = self.finished.read()
        return RunResult(days, c.rule.label, sorted(s.registered), realised, last)

    def _run_day(self, day: int) -> DayResult:
        s, c = self.state, self.config
        steps = dict(zip(PHASES, (self._registration, self._bidding, self._clearing, self._scheduling,
                                  self._realtime, self._settlement)))
        first = PHASE_ORDER["registration" if day == 1 else "bidding"]
        if self._resumed is not None:
            first = PHASE_ORDER[self._resumed[0]]
            self._await_agents()
            if first > PHASE_ORDER["clearing"]:
                self.clearing = clearing_of(c, s)
                if first == PHASE_ORDER["scheduling"]:  # some awards may not have gone out; agents ignore a repeat
                    self._publish_awards()
        timings = {}
        for phase in PHASES[first:]:
            start = time.monotonic()
            out = steps[phase]()
            timings[phase] = time.monotonic() - start
        self._resumed = None
        statements, totals, locked_out = out
        return DayResult(day, s.market_day, c.islanded(day), self.clearing, statements, totals, copy.copy(s), timings,
                         locked_out)

    def _settled_again(self, closed: DayState) -> DayResult:
        """A day finished before the DMO restarted, settled again from its journal (nothing is published)."""
        clearing = clearing_of(self.config, closed)
        statements, totals = settlement_of(self.config, closed, clearing)
        return DayResult(closed.day, closed.market_day, self.config.islanded(closed.day), clearing, statements,
                         totals, closed, {})

    def _registration(self) -> None:
        s, c = self.state, self.config
        self._clock("registration", c.registration_s)

        rule = intake.registration(s, c.network, c.placement)

        def accept(msg):
            refusal = rule(msg)
            if refusal is None:
                log.info("registered %s (%d/%d)", msg.sender, len(s.registered), c.agents)
            return refusal

        missing = lambda: [f"{c.agents - len(s.registered)} more agent(s)"] if len(s.registered) < c.agents else []
        self._wait(c.registration_s, missing, "registration", accept, name_late=False)
        if len(s.registered) < c.agents:
            self._incident(None, f"only {len(s.registered)} of {c.agents} agents registered by the deadline")
        if not s.registered:
            raise RuntimeError("no agent registered before the registration deadline")

    def _bidding(self) -> None:
        s, c = self.state, self.config
        self._clock("bidding", c.bids_s)
        self._bids_due = time.monotonic() + c.bids_s
        self._publish(outbox.call_for_bids(c, s.day, c.bids_s))
        self._wait(c.bids_s, lambda: self._unanswered(s.bids, "bid"), "bid", intake.first_of_each(s, s.bids))

    def _clearing(self) -> None:
        self._clock("clearing", self.config.bids_s)
        self.clearing = clearing_of(self.config, self.state)
        self._publish_awards()
        if isinstance(self.clearing, NetworkClearing):  # after the awards: the agents need not wait for the AC check
            at = feeder.sites(self.config, self.state)
            for msg in feeder.planned(self.config, self.state.day, self.clearing, at):
                self._publish(msg)

    def _publish_awards(self) -> None:
        at = feeder.sites(self.config, self.state)
        for agent in sorted(self.state.registered):
            self._publish(outbox.award(self.config, self.state.day, self.clearing, agent, at.get(agent)))

    def _scheduling(self) -> None:
        s, c = self.state, self.config
        self._clock("scheduling", c.schedule_s)
        self._wait(c.schedule_s, lambda: self._unanswered(s.schedules, "schedule"), "schedule",
                   intake.first_of_each(s, s.schedules))

    def _realtime(self) -> None:
        s, c = self.state, self.config
        first = self._resumed[1] if self._resumed and self._resumed[0] == "realtime" else 1
        room = None  # on a feeder, the day's operating envelope: once a day, from its clearing (a resumed day's too)
        if isinstance(self.clearing, NetworkClearing):
            room = feeder.envelope(c, self.clearing, feeder.sites(c, s))
        for hour in range(first, HOURS + 1):
            self._clock("realtime", c.hour_s, hour)
            self._grid = outbox.grid_state(c, s.day, hour, room)
            self._publish(self._grid)

            accept = intake.meter_report(s, hour, c.subperiods, self._grid)
            self._wait(c.hour_s, lambda: self._unanswered({a for a in s.meter if hour - 1 in s.meter[a]},
                                                          "meter_report", hour),
                       f"meter report for hour {hour}", accept)

    def _settlement(self) -> tuple[dict[str, Statement], DayTotals, tuple[str, ...]]:
        s, c = self.state, self.config
        self._clock("settlement", c.hour_s)
        while not self.events.empty():  # what arrived since the last hour closed is late, and recorded as such
            self._handle(self.events.get_nowait(), intake.out_of_phase(s))
        locked_out = tuple(s.guard.locked_out())
        for agent in locked_out:
            self._incident(agent, "locked out: a process of it spoke to the DMO, which did not admit it (its "
                                  "registration was refused, or never came)")
        for incident in s.log.close(s.phase, s.hour):
            log.warning("settlement: %s", incident.reason)
        statements, totals = settlement_of(c, s, self.clearing)
        if c.network is not None:
            for msg in feeder.realised(c, s.day, s, feeder.sites(c, s)):
                self._publish(msg)
        for st in statements.values():
            self._publish(outbox.statement_message(st, s.market_day, *c.rates, c.rule.label))
        self._publish(outbox.day_summary(s.market_day, s.registered, self.clearing.price, statements, s.rejected,
                                         s.incidents))
        return statements, totals, locked_out

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
        self._incident(None, f"the DMO restarted and resumed day {s.day} {_when(*self._resumed)} from its journal "
                             f"({sum(s.accepted.values())} accepted messages recovered)"
                             + (f"; not back: {', '.join(sorted(waiting))}" if waiting else ""))

    def _joined(self, name: str) -> None:
        s = self.state
        if name in s.gone and name in s.registered:
            s.gone.discard(name)
            since = s.vanished.get(name, (s.phase, None))
            self._incident(name, f"reappeared after vanishing {_when(*since)}{_outage(since, s.hour)}; "
                                 f"sent {self._resend(name)}")

    def _left(self, name: str) -> None:
        s = self.state
        if name in s.registered and name not in s.gone:
            if name in self.bus.present(timeout_s=self._presence_s):
                return  # an earlier process of it left; a restarted one is here (their tokens share the key)
            s.gone.add(name)
            s.vanished[name] = (s.phase, s.hour)
            if name in self.config.restarting:  # the run restarts it: a new process is on its way
                self._returning[name] = self._deadline(self.config.registration_s)
            self._incident(name, "vanished (liveliness lost); what it does not report is settled by the "
                                 "missing-data rule")

    def _unanswered(self, answered, kind: str, hour: int | None = None) -> list[str]:
        """The agents a phase or hour still waits for (``_awaited``) that have neither an accepted answer (in
        ``answered``) nor one of ``kind`` (for ``hour``) refused, nor gone over their budget in it."""
        return [a for a in self._awaited()
                if a not in answered and (a, kind, hour) not in self._refused and a not in self._over]

    def _awaited(self) -> list[str]:
        """The agents a phase or hour waits for: the live ones, and one the run restarts (``restarting``) from when
        it vanishes until it is back (on the wall clock, at most until a new process of it would be past the
        registration deadline; a phase or hour still ends at its own deadline). Without this a fast day ran its
        remaining hours in a second while the restarted process was still starting, and settled it as missing for 11
        to 24 of them."""
        now, s = time.monotonic(), self.state
        back = [a for a, until in self._returning.items() if a in s.gone and now < until]
        return sorted({*s.live(), *back})

    def _resend(self, agent: str) -> str:
        """Send an agent that comes back what it needs to go on; say what was sent."""
        kinds, said = rejoin.resend_plan(self.state, agent, self.clearing is not None, self._grid is not None)
        for kind in kinds:
            if kind == rejoin.CALL_FOR_BIDS:
                due = round(max(0.1, self._bids_due - time.monotonic()), 1)
                self._publish(outbox.call_for_bids(self.config, self.state.day, due))
            elif kind == rejoin.AWARD:
                self._publish(outbox.award(self.config, self.state.day, self.clearing, agent,
                                           feeder.sites(self.config, self.state).get(agent)))
            else:
                self._publish(self._grid)
        return said

    # --- plumbing ---------------------------------------------------------------------------------------------

    def _listen(self) -> None:
        self.bus.subscribe(f"{self.bus.keys.prefix}/agent/**", lambda k, m, t, p: self.events.put(Received(k, m, p)),
                           payload=True)
        self.bus.watch_presence(lambda name: self.events.put(Joined(name)), lambda name: self.events.put(Left(name)))
        self.bus.serve(self.bus.keys.everything(), self.history.answer, slow=asks_history)

    def _traffic(self, key: str, payload: bytes, at: int) -> None:
        """Every payload sent or received (the bus's tap, on Zenoh's threads too): kept for late joiners."""
        if self.history is not None:
            self.history.record(key, payload, at)

    def _admit(self, key: str, size: int) -> bool:
        """Whether a payload received on ``key`` is within its sender's budget (the bus's gate, on Zenoh's threads):
        the first one over it in a phase or hour tells the day (one incident); it and the rest are dropped unread."""
        sender = agent_of(key)
        dropped = self.budget.admit(sender, size)
        if dropped == 1:
            self.events.put(OverBudget(sender))
        return not dropped

    def _next_window(self) -> None:
        """A new phase or hour: every agent's budget starts afresh; what the last window dropped of each is the
        day's ``dropped_messages``."""
        self.state.dropped.update({a: n for a, n in self.budget.next_window().items() if a is not None})
        self._refused, self._over = set(), set()

    @property
    def _presence_s(self) -> float:
        """How long a presence check may take."""
        return PRESENCE_CHECK_LOGICAL_S if self.config.logical else PRESENCE_CHECK_S

    def _deadline(self, seconds: float) -> float:
        """When, on the monotonic clock, a wait of ``seconds`` ends: never on the logical clock."""
        return math.inf if self.config.logical else time.monotonic() + seconds

    def _publish(self, msg) -> None:
        self.bus.publish(msg)

    def _clock(self, phase: str, deadline_s: float, hour: int | None = None) -> None:
        s = self.state
        self._next_window()
        s.phase, s.hour = phase, hour
        if self.journal is not None:
            self.journal.clock(phase, hour, s.day, s.market_day)
        self.on_progress(phase, hour)
        self._publish(outbox.clock(self.config, s.day, phase, hour, deadline_s))

    def _incident(self, agent: str | None, reason: str) -> None:
        s = self.state
        incident = s.log.add(agent, s.phase, s.hour, reason)
        if self.journal is not None:
            self.journal.incident(incident)
        log.warning("%s%s: %s%s", s.phase, f" hour {s.hour}" if s.hour else "", f"{agent}: " if agent else "",
                    incident.reason)

    def _reject(self, key: str, payload: bytes, err: MessageError, offender: str | None, msg=None) -> None:
        """A payload refused: counted, listed, published as a Rejection, and its sender (the agent the key names)
        gets the refusal as its receipt."""
        if (msg is not None and err.code not in REPLAYS
                and msg.incarnation == self.state.guard.incarnation.get(msg.sender)):
            # an answer of the agent's admitted process, refused: it will not send it again (a payload that could not
            # be read is no answer: its sender cannot tell the refusal is of it, and sends it again; nor is one of
            # another process in its name)
            self._refused.add((offender, msg.kind, msg.hour if msg.kind == "meter_report" else None))
        listed = self.state.log.count_rejection(err.code)
        if self.journal is not None:
            self.journal.rejected(err.code)
        if listed:
            self._incident(offender, f"rejected message on {key.split('/', 2)[-1]}: {err.code}: {err.reason}")
        else:
            log.info("rejected message on %s: %s: %s", key, err.code, err.reason)
        self._publish(make_rejection(key, payload, err, market_day=self.state.market_day, offender=offender))
        if offender is not None:
            self._publish(make_receipt(offender, payload, err, market_day=self.state.market_day))

    def _wait(self, seconds: float, waiting_for: Callable[[], list[str]], what: str, accept,
              name_late: bool = True) -> None:
        """Handle events until nobody is ``waiting_for`` or, on the wall clock, ``seconds`` pass; then name the
        late agents.

        Halfway to a deadline (on the logical clock, every ``STILL_WAITING_S``) the DMO logs who it is waiting for,
        so a stall is never silent.
        """
        start = time.monotonic()
        deadline = self._deadline(seconds)
        say_at = start + (seconds / 2 if math.isfinite(deadline) else STILL_WAITING_S)
        while waiting_for():
            now = time.monotonic()
            if now >= deadline:
                for agent in waiting_for() if name_late else ():
                    self._incident(agent, f"late: no {what} by the deadline")
                return
            if now >= say_at:
                log.warning("%s: still waiting for %s from %s", self.state.phase, what, ", ".join(waiting_for()))
                say_at = deadline if math.isfinite(deadline) else now + STILL_WAITING_S
            try:
                event = self.events.get(timeout=max(0.05, min(deadline, say_at) - now))
            except queue.Empty:
                continue
            self._handle(event, accept)

    def _handle(self, event: Event, accept) -> None:
        if isinstance(event, OverBudget):
            self._over.add(event.agent)
            self._incident(event.agent, f"over its budget of {self.budget.messages} messages and {self.budget.size} "
                                        f"bytes in this {'hour' if self.state.hour else 'phase'}: what it sends more "
                                        "until the next is dropped unread (dropped_messages)")
        elif isinstance(event, Unreadable):
            self._reject(event.key, event.payload, event.error, agent_of(event.key))
        elif isinstance(event, Joined):
            self._joined(event.name)
        elif isinstance(event, Left):
            self._left(event.name)
        else:
            self._received(event.key, event.msg, event.payload, accept)

    def _received(self, key: str, msg, payload: bytes, accept) -> None:
        """A valid message from an agent, with the bytes it arrived as, decided by ``intake.receive``: what it took
        is journaled before its receipt goes (what is receipted survives a restart), a refusal is published, a
        rejoin is met with what the agent needs; every message gets its receipt."""
        outcome = intake.receive(self.state, msg, sha256(payload), accept, self.config.network,
                                 self.config.placement)
        if outcome.what == intake.REFUSED:
            code, reason = outcome.refusal
            return self._reject(key, payload, MessageError(reason, code), msg.sender, msg)
        if outcome.taken and self.journal is not None:
            self.journal.accepted(key, payload)
        if outcome.taken and isinstance(msg, AgentDay):
            self.finished.realised(msg)
        self._publish(make_receipt(msg.sender, payload, None, market_day=self.state.market_day))
        if outcome.what == intake.REJOINED:
            self._incident(msg.sender, f"rejoined: a restarted process of it registered again; sent "
                                       f"{self._resend(msg.sender)}")

    def _linger(self) -> None:
        """Stay until the live agents have left (they leave once they have the summary and what they sent is
        receipted), at most ``linger_s`` (the hour deadline unless set): the DMO is the agents' router, and closing
        at once could cut off the summary still on its way. What agents send meanwhile is decided and receipted as
        in settlement: a realised day of the last day is still taken. Then, if a recorder is present, wait (at most
        ``RECORDER_CHECK_S``) until it has asked for the traffic to its end (it asks as agents leave): what the
        network lost on its way there, the last day's statements and summary too, reaches the recording."""
        # an agent whose presence the DMO cannot see (a client that declares no liveliness token) is not waited for
        c = self.config
        waiting = set(self.state.live()) & self.bus.present(timeout_s=self._presence_s)
        deadline = self._deadline(c.hour_s if c.linger_s is None else c.linger_s)
        accept = intake.out_of_phase(self.state)
        while waiting and (left := deadline - time.monotonic()) > 0:
            try:
                event = self.events.get(timeout=min(left, STILL_WAITING_S))
            except queue.Empty:
                if math.isfinite(deadline):
                    break
                log.warning("settlement: still waiting for %s to leave", ", ".join(sorted(waiting)))
                continue
            if isinstance(event, Left):
                waiting.discard(event.name)
            elif not isinstance(event, Joined):
                self._handle(event, accept)
        self._next_window()
        recorder = RECORDER in self.bus.present(timeout_s=self._presence_s)
        if recorder and not self.history.wait_answered(RECORDER_CHECK_S):
            log.warning("the recorder did not ask for the run's last messages within %g s: the recording may lack "
                        "what the network lost on its way there", RECORDER_CHECK_S)


PRESENCE_CHECK_S = 0.5  # how long a presence check may hold the DMO up (an answer on one host takes milliseconds) ...
PRESENCE_CHECK_LOGICAL_S = 30.0  # ... on the logical clock, where one that a loaded machine delays must not misjudge
# Refusals of what is not an agent's answer of now: a copy or replay of an earlier message, a message of a process of
# it that is gone, or one overtaken by a later one (guard.py). Its answer may still come, so it is still waited for.
REPLAYS = ("duplicate", "stale", "late")
STILL_WAITING_S = 60.0  # on the logical clock, how often the DMO says who it is still waiting for
RECORDER_CHECK_S = 10.0  # how long a leaving DMO waits for the recorder to ask for what it may have missed


def _when(phase: str, hour: int | None) -> str:
    return f"in {phase}" + (f" hour {hour}" if hour else "")


def _outage(since: tuple[str, int | None] | None, hour: int | None) -> str:
    """How many hours an agent that vanished ``since`` (phase, hour) was gone, if it came back in a later hour."""
    if since and since[1] and hour and hour > since[1]:
        return f", {hour - since[1]} hour(s) later"
    return ""
