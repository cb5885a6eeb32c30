"""A microgrid agent's market days over a Bus: register once, then each day bid, schedule against the award and
operate hour by hour, carrying the microgrid's state across midnight into the next day.

Zenoh's callback threads only enqueue what arrives; the agent handles it in order on its main thread, so a long
solve delays, but never reorders or drops, what comes next. A day ends once the agent has the DMO's day summary
and its own statement (if the summary comes first, it asks the DMO for the statement and waits ``statement_s``,
then says it gave up); the run ends with the last day the DMO's clock announces, or when the agent hears nothing
for ``idle_s``.

Nothing is waited out for want of one message (docs/protocol.md, "Receipts and sending again"): what the agent
sends goes again until the DMO's receipt comes (delivery.py), and when the DMO has been silent for a while the
agent asks it for the latest of what it is waiting for (its clock, the call for bids, the award, the grid state,
the statement and summary). What the DMO sends is handled idempotently: a repeated call for bids or award, or the
grid state of an hour already operated, changes nothing. A grid state after a gap (the agent restarted, or lost
the DMO for a while) first brings the day up to that hour, unreported. A refusal in a receipt is logged with its
reason, and a refused registration ends the agent with that reason (exit 1).

What the agent realised is a message, not a log line: after the last meter report of each day it operated to its
end it sends an ``agent_day`` (its own cost, curtailment and state at midnight, the computation of each message it
handled, its message counts), receipted like everything it sends; its log lines are for people only.
"""

from __future__ import annotations

import collections
import logging
import queue
import time
from dataclasses import dataclass

import numpy as np

from messages import (Award, Bid, CallForBids, Clock, DaySummary, GridState, MessageError, MeterReport,
                      Receipt, Registration, Schedule, SettlementStatement, check_route, decode)
from messages.keys import parse_key
from messages.schemas import MAX_HANDLED, AgentDay, HandlingTime, MessageCounts, MidnightUnit
from messages.transport import Bus
from messages.transport.heap import return_free_memory
from scenarios import exact
from scenarios.case import Case
from scenarios.days import carry_over, day_scale, day_seed, market_days, scaled_profiles
from scenarios.generation import forecast_scenario, make_scenarios, sample
from scenarios.horizon import HOURS

from ..instance import Instance
from ..model import DeviationCost, Params, first_stage_of
from ..schedule import FirstStage
from .delivery import Delivery, RefusedPayload, Silence
from .realtime import Operator
from .slots import computing
from .strategies import (DEFAULT_STRATEGY, NO_BID, ChosenStrategy, DayLearned, Microgrid, StrategyError,
                         make_strategy, strategy_name)

log = logging.getLogger("dmosim.agent")


@dataclass(frozen=True)
class AgentConfig:
    """How the agent schedules: scenarios of its stochastic model, islanding hours it plans for, solver gap, time
    limit, route (microgrid_agent/solvers/routes.py) and Benders workers, and the seed of its own scenarios (``seed``)
    and of the day it will actually live (``seed + 1000``), each day of a run from its own (scenarios/days.py).
    ``load_scale`` and ``renewable_scale`` scale each day's forecasts, a pattern repeated over the days (e.g. a
    week: five weekdays, two lighter weekend days)."""

    scenarios: int
    island_hours: int
    gap: float
    time_limit: float | None
    seed: int
    method: str
    workers: int
    load_scale: tuple[float, ...]
    renewable_scale: tuple[float, ...]
    bus: str | None = None  # the bus of the market's feeder it registers at (None: a copper-plate market)
    idle_s: float = 3600.0  # without news from the DMO for this long, the agent gives up
    # After the day summary, how long to wait for the agent's own statement; and for the receipts of what it sent
    # before its agent_day (which must not overtake the last meter report: the DMO refuses a message older than one
    # it took). None: as long as idle_s, on the logical clock, where what the agent reports must not depend on how
    # busy the machine is.
    statement_s: float | None = 30.0
    receipts_s: float | None = 5.0

    def waits(self, seconds: float | None) -> float:
        """How long a wait set to ``seconds`` (statement_s, receipts_s) lasts."""
        return self.idle_s if seconds is None else seconds


class AgentTimeout(RuntimeError):
    pass


class AgentRefused(RuntimeError):
    """The DMO refused this agent's registration: the reason is the DMO's."""


class MicrogridAgent:
    """One microgrid through the market days of a run. ``case`` is its case as the run starts; each later day starts
    from the state the realised operation of the day before ended in (``scenarios.days.carry_over``). ``strategy``
    makes its bids (docs/strategies.md; default: the price response)."""

    def __init__(self, bus: Bus, case: Case, config: AgentConfig, market_day: str,
                 strategy: ChosenStrategy | None = None):
        self.bus, self.base, self.config, self.market_day = bus, case, config, market_day
        self.strategy = strategy or make_strategy(strategy_name(DEFAULT_STRATEGY))
        self.day, self.days = 1, 1
        self.case = self._day_case(case, 1)
        self.events: queue.Queue = queue.Queue()
        self._answering: tuple[float, float] | None = None  # perf_counter, thread_time as the answer went out
        self.delivery = Delivery(bus.republish)
        self.asked = 0  # messages the agent asked the DMO for (it had heard nothing for a while) and handled
        self.ignored: collections.Counter[str] = collections.Counter()  # messages handled as no-ops, by why
        self._ahead: list = []  # messages of a later market day than the one being run, kept for it
        self._first_stage: FirstStage | None = None  # of the latest schedule: the next day's solve starts from it
        self._start_day()

    def _start_day(self) -> None:
        """What the agent knows of the day being run: nothing yet."""
        self.operator: Operator | None = None
        self.award: Award | None = None
        self.statement: SettlementStatement | None = None
        self.summary: DaySummary | None = None
        self._bid_sent = False
        self._bid_hours = NO_BID  # what the bid sent offered, for the strategy's observe
        self._grid_seen: dict[int, GridState] = {}  # hour -> its grid state, of grid states not operated
        self.compute: list[HandlingTime] = []  # the day's messages handled, each with its computation
        self._realised_due = False  # the day has been operated to its end: its agent_day goes after its compute

    def _day_case(self, case: Case, day: int) -> Case:
        c = self.config
        return scaled_profiles(case, day_scale(c.load_scale, day), day_scale(c.renewable_scale, day))

    @property
    def id(self) -> str:
        return self.bus.name

    def run(self) -> DaySummary:
        try:
            return self._run()
        finally:
            self.delivery.close()

    def _run(self) -> DaySummary:
        k = self.bus.keys
        put = lambda key, msg, t: self.events.put(msg)  # noqa: E731
        for pattern in (k.clock(), k.call_for_bids(), k.award(self.id), k.grid(), k.statement(self.id),
                        k.summary()):
            self.bus.subscribe(pattern, put)
        self.bus.subscribe(k.receipt(self.id), self._receipt_arrived)
        self._join_where_the_run_is()  # the DMO has answered: it listens (docs/protocol.md, step 3)
        self.bus.wait_for_subscribers(k.register(self.id), self.config.idle_s)  # and this client knows it does
        grid = self.case.grid
        self._publish(Registration(sender=self.id, market_day=self.market_day, case=self.base.name,
                                   max_import_mw=grid.p_m_max, max_export_mw=grid.p_m_max,
                                   strategy=self.strategy.label, bus=self.config.bus))
        # Nothing else goes before the registration's receipt: a restarted process's bid, schedule or report would
        # be refused as unregistered (and not sent again) were it to overtake a lost registration.
        if not self.delivery.drained(self.config.idle_s):
            raise AgentTimeout(f"{self.id}: no receipt for my registration in {self.config.idle_s:g} s")
        log.info("%s registered", self.id)
        while True:
            self._run_day()
            if self.statement is None:
                self._await_statement()
            self._observe()
            if self.day >= self.days:
                break
            self._next_day()
        # The DMO lingers after the last summary (on the logical clock, until this agent leaves): what is still
        # unreceipted (the last agent_day) has that long.
        if not self.delivery.drained(LEAVING_S):
            log.warning("%s: leaving with %d payload(s) not receipted", self.id, self.delivery.waiting())
        return self.summary

    def _run_day(self) -> None:
        """Handle what comes until the day's summary."""
        while self.summary is None:
            msg = self._next_message()
            if isinstance(msg, RefusedPayload):  # no computation to account for
                self._handle(msg)
                continue
            started_at, self._answering = time.time_ns(), None
            # CPU of this thread: agents sharing a process each count their own (the process's counted, in each
            # agent that waited for its turn, what the others computed meanwhile)
            started = (time.perf_counter(), time.thread_time())
            with computing():  # a turn among the agents of a host (slots.py): waiting counts in wall_s and turn_s
                turn_s = time.perf_counter() - started[0]
                self._handle(msg)
            ended = self._answering or (time.perf_counter(), time.thread_time())
            self.compute.append(HandlingTime(kind=msg.kind, hour=getattr(msg, "hour", None),
                                             wall_s=ended[0] - started[0], cpu_s=ended[1] - started[1],
                                             started_at=started_at, turn_s=turn_s))
            if self._realised_due:  # after the compute of the last grid state, which it carries
                self._realised_due = False
                self._send_realised()
                return_free_memory()  # the day's hours are over: what their models took from the C heap goes back

    def _next_message(self):
        """The next message from the DMO. When it has been silent for a while, ask it for the latest of what this
        agent waits for (a message of it may have been lost), then again at doubling intervals; give up after
        ``idle_s`` of silence."""
        silence = Silence(self.config.idle_s, time.monotonic(), ASK_AFTER_S, ASK_AT_MOST_S)
        wait = silence.wait
        while True:
            try:
                return self.events.get(timeout=wait)
            except queue.Empty:
                pass
            if silence.over(time.monotonic()):
                raise AgentTimeout(f"{self.id}: nothing from the DMO for {self.config.idle_s:g} s")
            self._ask_the_dmo()
            wait = silence.asked(time.monotonic())

    def _ask_the_dmo(self) -> None:
        """Ask the DMO (docs/protocol.md, "Asking the DMO") for the latest message on each key this agent waits on,
        and handle the answers as if they had come: what was handled already is a no-op."""
        k = self.bus.keys
        answers = self._latest([k.clock()])
        if any(m.kind == "clock" and m.phase == "registration" for m in answers):
            keys = []  # the DMO sends nothing else before registration closes (a thousand agents asking it for
            # five keys each while they registered kept it too busy to answer)
        else:
            keys = [] if self._bid_sent else [k.call_for_bids()]
            if self.award is None:
                keys.append(k.award(self.id))
            elif self.operator is not None and self.operator.next_hour <= HOURS:
                keys.append(k.grid())
            if self.statement is None:
                keys.append(k.statement(self.id))
            if self.summary is None:
                keys.append(k.summary())
        for msg in answers + self._latest(keys):
            if msg.kind == "clock" or (msg.market_day == self.market_day and self._new(msg)):
                self.asked += 1
                self.events.put(msg)

    def _new(self, msg) -> bool:
        """Whether an answer of the DMO's tells this agent something it has not handled yet."""
        if isinstance(msg, CallForBids):
            return not self._bid_sent
        if isinstance(msg, Award):
            return self.award is None
        if isinstance(msg, GridState):
            return self.operator is None or msg.hour >= self.operator.next_hour
        if isinstance(msg, SettlementStatement):
            return self.statement is None
        return isinstance(msg, DaySummary) and self.summary is None

    def _latest(self, keys: list[str], timeout_s: float | None = None) -> list:
        """The DMO's latest valid message of this run on each of ``keys`` (none where it answers nothing), each
        answer waited for ``timeout_s`` (``ANSWER_S`` unless given)."""
        out = []
        for key in keys:
            for found, payload, _ in self.bus.fetch(key, timeout_s=timeout_s or ANSWER_S):
                try:
                    msg = decode(payload, expected_kind=parse_key(found).kind)
                    check_route(found, msg, self.bus.keys.run_id)
                except MessageError as err:
                    log.warning("%s: the DMO's answer on %s is refused: %s", self.id, found, err)
                    continue
                if msg.run == self.bus.run_token or not self.bus.run_token:
                    out.append(msg)
        return out

    def _join_where_the_run_is(self) -> None:
        """Ask the DMO for its clock (docs/protocol.md, "Asking the DMO") until it answers, at most ``idle_s``: its
        answer gives the run's token, which every message carries, and where the run is. An agent started, or
        restarted, after the run began joins its current day."""
        deadline, wait = time.monotonic() + self.config.idle_s, ANSWER_S
        while True:
            asked = time.monotonic()
            if clocks := self._latest([self.bus.keys.clock()], wait):
                break
            if time.monotonic() >= deadline:
                raise AgentTimeout(f"{self.id}: the DMO did not answer for {self.config.idle_s:g} s")
            if time.monotonic() - asked >= wait:  # it is there but busy (a thousand agents joining): wait longer
                wait = min(2 * wait, ASK_AT_MOST_S)
            else:
                time.sleep(ASK_AFTER_S / 4)  # a DMO not up yet answers nothing, at once
        clock = clocks[0]
        self.bus.run_token = clock.run
        self.days, self.market_day = clock.days, clock.market_day  # the DMO's day, whatever we were told
        if clock.day > 1:
            self.day = clock.day
            self.case = self._day_case(self.base, clock.day)
            log.warning("%s: the run is at day %d of %d (%s): joining it there, from the case's own initial "
                        "state", self.id, clock.day, clock.days, clock.market_day)

    def _next_day(self) -> None:
        """Carry the microgrid across midnight: the next day's case starts where the realised operation ended."""
        done = self.operator is not None and self.operator.next_hour > HOURS
        case = self._day_case(self.base, self.day + 1)
        if done:
            midnight = self.operator.midnight()
            log.info("%s: day %d starts from midnight: units on %s, storage %s MWh", self.id, self.day + 1,
                     [u.name for u, on in zip(self.case.units, midnight.unit_on) if on], midnight.stored_mwh)
            case = carry_over(case, midnight, name=f"{self.base.name}-day{self.day + 1}")
        else:
            log.warning("%s: day %d was not operated to its end: day %d starts from the case's initial state",
                        self.id, self.day, self.day + 1)
        self.day += 1
        self.market_day = market_days(self.market_day, 2)[1]
        self.case = case
        self._start_day()
        ahead, self._ahead = self._ahead, []
        for msg in ahead:
            self.events.put(msg)
        log.info("%s: day %d of %d, %s", self.id, self.day, self.days, self.market_day)

    def _await_statement(self) -> None:
        """The summary came before the agent's own statement (messages on different keys may overtake each other,
        or the statement was lost): ask the DMO for it, then wait up to ``statement_s``; say so if it never came."""
        k, wait = self.bus.keys, self.config.waits(self.config.statement_s)
        for key, payload, _ in self.bus.fetch(k.statement(self.id), timeout_s=min(5.0, wait)):
            try:
                msg = decode(payload, expected_kind="settlement_statement")
                check_route(key, msg, k.run_id)
            except MessageError as err:
                log.warning("%s: the DMO's answer for my statement is refused: %s", self.id, err)
                continue
            self.events.put(msg)
        deadline = time.monotonic() + wait
        while self.statement is None and (left := deadline - time.monotonic()) > 0:  # receipts may still come
            try:
                self._handle(self.events.get(timeout=left))
            except queue.Empty:
                break
        if self.statement is None:
            log.warning("%s: gave up waiting for my settlement statement %g s after the day summary", self.id,
                        wait)

    def message_counts(self) -> MessageCounts:
        """What the agent's process published, received and refused (transport), handled as no-ops, sent again,
        asked for and injected as faults, since it started."""
        faults = self.bus.faults_injected()
        stats = self.bus.stats()
        return MessageCounts(published=stats["published"], received=stats["received"], rejected=stats["rejected"],
                             handler_errors=stats["handler_errors"], ignored=dict(self.ignored),
                             sent_again=self.delivery.resent, asked=self.asked, faults_injected=faults)

    def _publish(self, msg) -> None:
        """Publish, and send again until the DMO's receipt comes."""
        self.bus.publish(msg, before_put=self.delivery.sent)

    def _receipt_arrived(self, key: str, receipt: Receipt, received_at: int) -> None:
        """On Zenoh's thread: stop sending the payload again at once (the main thread may be solving), then let the
        main thread see a refusal."""
        if receipt.run != self.bus.run_token:
            return
        mine = self.delivery.receipt(receipt)
        if mine is not None and not receipt.accepted:
            self.events.put(RefusedPayload(receipt, *mine))

    def _answer(self, msg) -> None:
        """Publish the answer to the message being handled. Its computation ends as it goes out: sending it is the
        protocol's work, and what the handler does afterwards overlaps the DMO's next step."""
        self._answering = time.perf_counter(), time.thread_time()
        self._publish(msg)

    def _handle(self, msg) -> None:
        if isinstance(msg, RefusedPayload):
            return self._refused(msg)
        if msg.run != self.bus.run_token:
            self.ignored["wrong_run"] += 1
            log.warning("%s: ignoring %s of another run (token %r)", self.id, msg.kind, msg.run)
            return
        if (self.day < self.days and msg.market_day == market_days(self.market_day, 2)[1]
                and len(self._ahead) < MAX_AHEAD):
            self._ahead.append(msg)  # the DMO has started the next day while this one waits for its statement
        elif msg.market_day != self.market_day:
            self.ignored["wrong_day"] += 1
            log.warning("%s: ignoring %s for market day %s", self.id, msg.kind, msg.market_day)
        elif isinstance(msg, Clock):
            self._clock(msg)
        elif isinstance(msg, CallForBids):
            if self._bid_sent:
                self.ignored["call_for_bids_again"] += 1
                log.info("%s: call for bids again; the bid already sent stands", self.id)
            else:
                self._bid(msg)
        elif isinstance(msg, Award):
            if self.award is not None and _terms(msg) == _terms(self.award):
                self.ignored["award_again"] += 1
                log.info("%s: the same award again; the schedule already solved stands", self.id)
            else:
                self._schedule(msg)
                return_free_memory()  # the day's solves are over: the memory their models and solvers used goes back
        elif isinstance(msg, GridState):
            self._operate(msg)
        elif isinstance(msg, SettlementStatement):
            self.statement = msg
            log.info("%s statement: total $%.2f (penalty $%.2f)", self.id, msg.total, msg.deviation_penalty)
        elif isinstance(msg, DaySummary):
            self.summary = msg

    def _bid(self, call: CallForBids) -> None:
        """The strategy's bid, checked. A strategy that fails (raises, or returns what is not a bid) costs the agent
        that day's market, not the run: one line says why, and the bid offers nothing in any hour (docs/strategies.md,
        "When a strategy fails")."""
        microgrid = Microgrid(self.id, self.case, self.day, self.market_day, day_seed(self.config.seed, self.day),
                              self.config.gap)
        try:
            curve = self.strategy.bid(call, microgrid)
        except StrategyError as err:
            log.warning("%s: %s; bidding nothing on day %d", self.id, err, self.day)
            curve = NO_BID
        self._answer(Bid(sender=self.id, market_day=self.market_day, hours=curve))
        self._bid_sent, self._bid_hours = True, curve
        log.info("%s bid sent", self.id)

    def _observe(self) -> None:
        """Tell the strategy what the day brought; one that fails to listen is said in one line, and bids on."""
        try:
            self.strategy.observe(DayLearned(self.day, self.market_day, self._bid_hours, self.award,
                                             self.statement, self.summary))
        except StrategyError as err:
            log.warning("%s: %s", self.id, err)

    def _schedule(self, award: Award) -> None:
        """The stochastic schedule of the paper against the award (objective (1), constraints (2)-(21))."""
        self.award = award
        c, k = self.config, award.subperiods
        scen = make_scenarios(self.case, c.scenarios, k, c.island_hours, seed=day_seed(c.seed, self.day))
        params = award_params(award)
        schedule = Instance(self.case, scen, params).solve(method=c.method, workers=c.workers, gap=c.gap,
                                                           time_limit=c.time_limit, start=self._first_stage)
        self._first_stage = schedule.first  # the next day's solve starts from it
        realised = sample(self.case, 1, k, island_hours=0, seed=day_seed(c.seed, self.day) + 1000)
        self.operator = Operator(self.case, first_stage_of(schedule), params.p_sch, params.penalty, k, realised,
                                 forecast_scenario(self.case, k), deviation_cost=params.deviation_cost)
        p_m_hourly = exact.matvec(schedule.dispatch.p_m.T, schedule.probability).reshape(HOURS, k).mean(axis=1)
        self._answer(Schedule(
            sender=self.id, market_day=self.market_day, status=schedule.status,
            commitment={n: tuple(int(x) for x in schedule.commitment[n]) for n in schedule.unit_names},
            expected_cost=float(schedule.objective), p_m_expected_mw=tuple(float(x) for x in p_m_hourly),
            scenarios=schedule.scenarios, mip_gap=float(schedule.mip_gap)))
        log.info("%s scheduled: expected cost $%.2f, gap %.3f%%", self.id, schedule.objective, 100 * schedule.mip_gap)
        if self._grid_seen:  # grid states came first (the agent rejoined mid-day): operate up to the latest, report it
            self._operate(self._grid_seen[max(self._grid_seen)])

    def _clock(self, clock: Clock) -> None:
        """The clock says how many days the run has. (An answer the DMO lost, restarting, needs nothing here: it
        had no receipt, so it is still being sent.)"""
        self.days = clock.days

    def _refused(self, refused: RefusedPayload) -> None:
        receipt, kind, seq = refused.receipt, refused.kind, refused.seq
        log.warning("%s: the DMO refused my %s #%d (%s): %s", self.id, kind, seq, receipt.code, receipt.reason)
        if kind == "registration" and receipt.code != "duplicate":
            raise AgentRefused(f"{self.id}: the DMO refused the registration ({receipt.code}): {receipt.reason}")

    def _operate(self, grid: GridState) -> None:
        if grid.subperiods != (self.award.subperiods if self.award else grid.subperiods):
            self.ignored["grid_state_wrong_subperiods"] += 1
            log.warning("%s: grid state with %d sub-periods, the award has %d; ignored", self.id, grid.subperiods,
                        self.award.subperiods)
            return
        if self.operator is None:
            self._grid_seen[grid.hour] = grid
            log.warning("%s: grid state for hour %d before any award; no report", self.id, grid.hour)
            return
        if grid.hour < self.operator.next_hour:
            self.ignored["grid_state_of_an_operated_hour"] += 1
            log.info("%s: grid state for hour %d again; already operated", self.id, grid.hour)
            return
        if grid.hour > self.operator.next_hour:
            first = self.operator.next_hour
            self.operator.catch_up(grid.hour, {h: seen.connected for h, seen in self._grid_seen.items()})
            log.warning("%s: no grid state for hour(s) %d..%d: operated them unreported (the DMO settles them as "
                        "missing)", self.id, first, grid.hour - 1)
        room = self._room(grid)
        result = self.operator.operate_hour(grid.hour, grid.connected, room)
        if result.surplus.any():
            log.warning("%s: hour %d islanded: %.3f MWh of generation had nowhere to go and was let out "
                        '(docs/agent.md, "Feasibility")', self.id, grid.hour, result.surplus.sum() / grid.subperiods)
        if result.envelope_infeasible:
            self.ignored["envelope_infeasible"] += 1
            log.warning("%s: hour %d cannot be operated within its operating envelope (%g MW either side of the "
                        "award): operated without it", self.id, grid.hour, room)
        self._answer(MeterReport(sender=self.id, market_day=self.market_day, hour=grid.hour,
                                 subperiods=grid.subperiods, p_m_mw=tuple(float(x) for x in result.p_m),
                                 deviation_mw=tuple(float(x) for x in result.deviation)))
        if self.operator.next_hour > HOURS:
            self._realised_due = True

    def _room(self, grid: GridState) -> float | None:
        """The room the grid state's operating envelope gives this microgrid's bus (docs/network.md, "Operating
        envelopes"): the bus its award names, else the one it registered at. None: the grid state carries no envelope
        (the copper plate), or none for that bus."""
        bus = self.award.bus if self.award.bus is not None else self.config.bus
        if bus is None or bus not in grid.buses:
            return None
        return grid.room_mw[grid.buses.index(bus)]

    def _send_realised(self) -> None:
        """The operated day as the agent alone knows it (docs/protocol.md, ``agent_day``): its own cost by term ($),
        the load it curtailed and the import above its award (MWh), its state at midnight, the computation of the
        day's messages handled so far and its message counts. The DMO records it and settles nothing by it."""
        if not self.delivery.drained(wait := self.config.waits(self.config.receipts_s)):
            log.warning("%s: my last meter report has no receipt after %g s; sending my realised day anyway", self.id,
                        wait)
        day, midnight = self.operator.day_result(), self.operator.midnight()
        dispatch, k = day.schedule.dispatch, day.schedule.subperiods
        cost = day.cost
        msg = AgentDay(
            sender=self.id, market_day=self.market_day, generation=cost.generation, startup=cost.startup,
            curtailment=cost.curtailment, penalty=cost.penalty, total=cost.total,
            curtailment_mwh=float(dispatch.load_shed.sum()) / k, deviation_mwh=float(dispatch.dp_plus.sum()) / k,
            units={u.name: MidnightUnit(on=on, output_mw=out, hours=h) for u, on, out, h in
                   zip(self.case.units, midnight.unit_on, midnight.unit_output_mw, midnight.unit_hours)},
            stored_mwh=midnight.stored_mwh, compute=tuple(self.compute[:MAX_HANDLED]),
            messages=self.message_counts())
        self._publish(msg)
        log.info("%s realised day %d: own cost $%.2f, curtailed %.3f MWh", self.id, self.day, cost.total,
                 msg.curtailment_mwh)


MAX_AHEAD = 1000  # messages of the next day kept while this one ends (the DMO sends a few dozen a day)
LEAVING_S = 5.0  # how long a leaving agent waits for the receipts of what it sent last (a DMO that left sends none)
ASK_AFTER_S = 1.0     # silence after which the agent asks the DMO for what it waits for ...
ASK_AT_MOST_S = 8.0   # ... then at doubling intervals up to this
ANSWER_S = 2.0        # how long the DMO's answer is waited for; joining, doubled up to ASK_AT_MOST_S while it is busy


def _terms(award: Award) -> dict:
    """An award's content, without the envelope that differs between copies (seq, sent_at)."""
    return award.model_dump(exclude={"seq", "sent_at"})


def award_params(award: Award) -> Params:
    """What the schedule is solved against: the award P^sch and the announced rule's price of a deviation
    (docs/settlement.md, "What agents schedule against"). The paper's rule is its own term c ΔP+ of (19)-(21); a
    rule the award gives no pieces for (a user's own) is scheduled against that term at the award's penalty."""
    p_sch = np.asarray(award.p_sch_mw, float)
    cost = None if award.deviation_cost is None else DeviationCost.from_pieces(award.deviation_cost)
    if cost is not None and cost.paper_rate() is not None:
        return Params(p_sch, cost.paper_rate())
    return Params(p_sch, award.penalty_per_mwh, deviation_cost=cost)
