"""What a microgrid agent decides through the market days of a run, as a state machine with no network, thread or
clock (sans IO, as h11 and wsproto are): each event goes in, and what the agent does about it comes out.

The events are the DMO's messages, a refusal of what the agent sent (``RefusedPayload``), the result of a solve
(``Solved``), the computation of each message its driver handled (``Handled``) and a statement that never came
(``NoStatement``). The actions are what the driver carries out, in order: ``Send`` a message (again until its receipt
comes), ``AwaitReceipts`` of everything sent so far before the next ``Send``, ``AskStatement`` of the DMO, and
``Solve`` the schedule: the one long computation of a day is the driver's to run where it likes (on its own thread,
or beside other agents' in worker processes), and the machine goes on when its result is handed in. The driver over
Zenoh is ``process.MicrogridAgent``, in one process ``dmosim.launch.inprocess``; the decisions are all here, so that
they are the same whoever drives them and are tested by handing messages in.

The agent registers once, then each day bids, schedules against the award and operates hour by hour, carrying the
microgrid's state across midnight into the next day. A day ends once the agent has the DMO's day summary and its own
statement (if the summary comes first, the driver asks the DMO for the statement; ``NoStatement`` if none came); the
run ends with the last day the DMO's clock announces (``done``). What the DMO sends is handled idempotently: a
repeated call for bids or award, or the grid state of an hour already operated, changes nothing but the ``ignored``
count. A grid state after a gap (the agent restarted, or lost the DMO for a while) first brings the day up to that
hour, unreported. A refusal is logged with its reason, and a refused registration raises ``AgentRefused``.

What the agent realised is a message, not a log line: after the last meter report of each day it operated to its
end it sends an ``agent_day`` (its own cost, curtailment and state at midnight, the computation of each message it
handled, its message counts); its log lines are for people only.
"""

from __future__ import annotations

import collections
import logging
from dataclasses import dataclass

import numpy as np

from messages import (Award, Bid, CallForBids, Clock, DaySummary, GridState, Message, MeterReport, Registration,
                      Schedule, SettlementStatement)
from messages.schemas import MAX_HANDLED, AgentDay, HandlingTime, MessageCounts, MidnightUnit
from scenarios import exact
from scenarios.case import Case
from scenarios.days import carry_over, day_scale, day_seed, market_days, scaled_profiles
from scenarios.generation import forecast_scenario, make_scenarios, sample
from scenarios.horizon import HOURS

from ..instance import Instance
from ..model import DeviationCost, Params, first_stage_of
from ..schedule import FirstStage, StochasticSchedule
from .delivery import RefusedPayload
from .realtime import Operator, Room
from .strategies import (DEFAULT_STRATEGY, NO_BID, ChosenStrategy, DayLearned, Microgrid, StrategyError,
                         make_strategy, strategy_name)

log = logging.getLogger("dmosim.agent")

MAX_AHEAD = 1000  # messages of the next day kept while this one ends (the DMO sends a few dozen a day)


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


class AgentRefused(RuntimeError):
    """The DMO refused this agent's registration: the reason is the DMO's."""


@dataclass(frozen=True)
class Send:
    """Publish ``msg`` (unstamped: the transport stamps it) and send it again until the DMO's receipt for it comes."""

    msg: Message


@dataclass(frozen=True)
class AwaitReceipts:
    """Hold the next ``Send`` until everything sent so far has its receipt, or ``receipts_s`` passed (then say so):
    the agent_day must not overtake the last meter report, since the DMO refuses a message older than one it took."""


@dataclass(frozen=True)
class AskStatement:
    """The day summary came before the agent's own statement (messages on different keys may overtake each other,
    or the statement was lost): ask the DMO for it and wait up to ``statement_s``, then, if none came, hand in
    ``NoStatement``."""


@dataclass(frozen=True)
class ScheduleJob:
    """The solve of a day's stochastic schedule against its award (objective (1), constraints (2)-(21)): the instance
    and how to solve it (microgrid_agent/solvers/routes.py), from the day before's first stage (``start``). A plain
    value that pickles, so that a driver may run it in another process."""

    instance: Instance
    method: str
    workers: int
    gap: float
    time_limit: float | None
    start: FirstStage | None

    def run(self) -> StochasticSchedule:
        return self.instance.solve(method=self.method, workers=self.workers, gap=self.gap,
                                   time_limit=self.time_limit, start=self.start)


@dataclass(frozen=True)
class Solve:
    """Run ``job`` and hand its schedule in (``Solved``), before any other event of this agent's: always the last
    action of its batch. The solve is part of the handling of the message that asked for it, and its computation
    counts in that message's."""

    job: ScheduleJob


Action = Send | AwaitReceipts | AskStatement | Solve


@dataclass(frozen=True)
class Solved:
    """The schedule that the job of the last ``Solve`` gave."""

    schedule: StochasticSchedule


@dataclass(frozen=True)
class Handled:
    """The driver handled a message of the DMO's: its computation, and the process's message counts by then (what
    the agent_day of a day just operated to its end reports; their ``ignored`` is the machine's to fill in)."""

    compute: HandlingTime
    counts: MessageCounts


@dataclass(frozen=True)
class NoStatement:
    """The statement asked for (``AskStatement``) did not come: the day ends without it."""


class AgentMachine:
    """One microgrid through the market days of a run: ``handle`` takes each event and returns the actions that
    follow. ``case`` is its case as the run starts; each later day starts from the state the realised operation of
    the day before ended in (``scenarios.days.carry_over``). ``strategy`` makes its bids (docs/strategies.md;
    default: the price response)."""

    def __init__(self, name: str, case: Case, config: AgentConfig, market_day: str,
                 strategy: ChosenStrategy | None = None):
        self.name, self.base, self.config, self.market_day = name, case, config, market_day
        self.strategy = strategy or make_strategy(strategy_name(DEFAULT_STRATEGY))
        self.run_token = ""  # the run's token, which every message carries: the DMO's clock gives it (join)
        self.day, self.days = 1, 1
        self.done = False  # the last day of the run has ended
        self.case = self._day_case(case, 1)
        self.ignored: collections.Counter[str] = collections.Counter()  # messages handled as no-ops, by why
        self._ahead: list = []  # messages of a later market day than the one being run, kept for it
        self._first_stage: FirstStage | None = None  # of the latest schedule: the next day's solve starts from it
        self._solving: ScheduleJob | None = None  # the solve out (a Solve), until its Solved comes
        self._after_solve: list = []  # messages the machine had to handle after the one that asked for the solve
        self._start_day()
        self._counted_in = self.compute  # the day the computation of the message being handled counts in

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

    def join(self, clock: Clock) -> None:
        """Where the run is, by the DMO's clock: the run's token, its days and the day it is at. An agent started,
        or restarted, after the run began joins its current day."""
        self.run_token = clock.run
        self.days, self.market_day = clock.days, clock.market_day  # the DMO's day, whatever we were told
        if clock.day > 1:
            self.day = clock.day
            self.case = self._day_case(self.base, clock.day)
            log.warning("%s: the run is at day %d of %d (%s): joining it there, from the case's own initial "
                        "state", self.name, clock.day, clock.days, clock.market_day)

    def registration(self) -> Registration:
        """The registration to send (docs/protocol.md, step 4): nothing else goes before its receipt."""
        grid = self.case.grid
        return Registration(sender=self.name, market_day=self.market_day, case=self.base.name,
                            max_import_mw=grid.p_m_max, max_export_mw=grid.p_m_max, strategy=self.strategy.label,
                            bus=self.config.bus)

    def handle(self, event) -> list[Action]:
        """What the agent does about ``event``: a message of the DMO's, a ``RefusedPayload``, ``Solved``, ``Handled``
        or ``NoStatement``. A refused registration raises ``AgentRefused``; an event other than ``Solved`` while a
        solve is out, or ``Solved`` while none is, raises ``RuntimeError`` (the driver broke its part, ``Solve``)."""
        if (self._solving is not None) != isinstance(event, Solved):
            out = "a solve is out" if self._solving is not None else "no solve is out"
            raise RuntimeError(f"{self.name}: {type(event).__name__} handed in while {out}")
        if isinstance(event, Solved):
            return self._solved(event.schedule)
        if isinstance(event, Handled):
            return self._handled(event)
        if isinstance(event, NoStatement):
            return self._end_day()
        if isinstance(event, RefusedPayload):
            return self._refused(event)
        self._counted_in = self.compute
        return self._handle(event)

    def wants(self, msg) -> bool:
        """Whether an answer of the DMO's to the agent's asking tells it something it has not handled yet: its
        clock always (where the run is), else a message of the day being run that it still waits for."""
        if isinstance(msg, Clock):
            return True
        if msg.market_day != self.market_day:
            return False
        if isinstance(msg, CallForBids):
            return not self._bid_sent
        if isinstance(msg, Award):
            return self.award is None
        if isinstance(msg, GridState):
            return self.operator is None or msg.hour >= self.operator.next_hour
        if isinstance(msg, SettlementStatement):
            return self.statement is None
        return isinstance(msg, DaySummary) and self.summary is None

    def waiting_for(self, registration_phase: bool) -> list[str]:
        """The kinds of the DMO's messages the agent waits for, which it asks the DMO for, after its clock, when it
        has heard nothing for a while (docs/protocol.md, "Asking the DMO"). None while the clock says registration:
        the DMO sends nothing else before registration closes (a thousand agents asking it for five keys each while
        they registered kept it too busy to answer)."""
        if registration_phase:
            return []
        kinds = [] if self._bid_sent else ["call_for_bids"]
        if self.award is None:
            kinds.append("award")
        elif self.operator is not None and self.operator.next_hour <= HOURS:
            kinds.append("grid_state")
        if self.statement is None:
            kinds.append("settlement_statement")
        if self.summary is None:
            kinds.append("day_summary")
        return kinds

    def _handle(self, msg) -> list[Action]:
        if msg.run != self.run_token:
            self.ignored["wrong_run"] += 1
            log.warning("%s: ignoring %s of another run (token %r)", self.name, msg.kind, msg.run)
            return []
        if (self.day < self.days and msg.market_day == market_days(self.market_day, 2)[1]
                and len(self._ahead) < MAX_AHEAD):
            self._ahead.append(msg)  # the DMO has started the next day while this one waits for its statement
            return []
        if msg.market_day != self.market_day:
            self.ignored["wrong_day"] += 1
            log.warning("%s: ignoring %s for market day %s", self.name, msg.kind, msg.market_day)
            return []
        if isinstance(msg, Clock):
            return self._clock(msg)
        if isinstance(msg, CallForBids):
            if not self._bid_sent:
                return self._bid(msg)
            self.ignored["call_for_bids_again"] += 1
            log.info("%s: call for bids again; the bid already sent stands", self.name)
            return []
        if isinstance(msg, Award):
            if self.award is None or _terms(msg) != _terms(self.award):
                return self._schedule(msg)
            self.ignored["award_again"] += 1
            log.info("%s: the same award again; the schedule already solved stands", self.name)
            return []
        if isinstance(msg, GridState):
            return self._operate(msg)
        if isinstance(msg, SettlementStatement):
            self.statement = msg
            log.info("%s statement: total $%.2f (penalty $%.2f)", self.name, msg.total, msg.deviation_penalty)
            return [] if self.summary is None else self._end_day()
        if isinstance(msg, DaySummary):
            asked, self.summary = self.summary is not None, msg
            if self.statement is not None:
                return self._end_day()
            return [] if asked else [AskStatement()]
        return []

    def _bid(self, call: CallForBids) -> list[Action]:
        """The strategy's bid, checked. A strategy that fails (raises, or returns what is not a bid) costs the agent
        that day's market, not the run: one line says why, and the bid offers nothing in any hour (docs/strategies.md,
        "When a strategy fails")."""
        microgrid = Microgrid(self.name, self.case, self.day, self.market_day, day_seed(self.config.seed, self.day),
                              self.config.gap)
        try:
            curve = self.strategy.bid(call, microgrid)
        except StrategyError as err:
            log.warning("%s: %s; bidding nothing on day %d", self.name, err, self.day)
            curve = NO_BID
        self._bid_sent, self._bid_hours = True, curve
        log.info("%s bid sent", self.name)
        return [Send(Bid(sender=self.name, market_day=self.market_day, hours=curve))]

    def _schedule(self, award: Award) -> list[Action]:
        """The stochastic schedule of the paper against the award (objective (1), constraints (2)-(21)), for the
        driver to solve (``Solve``)."""
        self.award = award
        c, k = self.config, award.subperiods
        scen = make_scenarios(self.case, c.scenarios, k, c.island_hours, seed=day_seed(c.seed, self.day))
        self._solving = ScheduleJob(Instance(self.case, scen, award_params(award)), c.method, c.workers, c.gap,
                                    c.time_limit, self._first_stage)
        return [Solve(self._solving)]

    def _solved(self, schedule: StochasticSchedule) -> list[Action]:
        """The award's schedule is solved: the day is operated by it, and the DMO told of it. Grid states that came
        before it are operated up to the latest, and the messages that waited for it are handled."""
        c, k, params = self.config, self.award.subperiods, self._solving.instance.params
        self._solving = None
        self._first_stage = schedule.first  # the next day's solve starts from it
        realised = sample(self.case, 1, k, island_hours=0, seed=day_seed(c.seed, self.day) + 1000)
        self.operator = Operator(self.case, first_stage_of(schedule), params.p_sch, params.penalty, k, realised,
                                 forecast_scenario(self.case, k), deviation_cost=params.deviation_cost)
        p_m_hourly = exact.matvec(schedule.dispatch.p_m.T, schedule.probability).reshape(HOURS, k).mean(axis=1)
        log.info("%s scheduled: expected cost $%.2f, gap %.3f%%", self.name, schedule.objective,
                 100 * schedule.mip_gap)
        actions: list[Action] = [Send(Schedule(
            sender=self.name, market_day=self.market_day, status=schedule.status,
            commitment={n: tuple(int(x) for x in schedule.commitment[n]) for n in schedule.unit_names},
            expected_cost=float(schedule.objective), p_m_expected_mw=tuple(float(x) for x in p_m_hourly),
            scenarios=schedule.scenarios, mip_gap=float(schedule.mip_gap)))]
        if self._grid_seen:  # grid states came first (the agent rejoined mid-day): operate up to the latest, report it
            actions += self._operate(self._grid_seen[max(self._grid_seen)])
        waited, self._after_solve = self._after_solve, []
        return actions + self._in_order(waited)

    def _in_order(self, msgs: list) -> list[Action]:
        """Handle ``msgs`` one after the other. Once one asks for a solve, the rest wait for its result (``Solved``),
        as they waited when the solve was called in line."""
        actions: list[Action] = []
        for i, msg in enumerate(msgs):
            actions += self._handle(msg)
            if self._solving is not None:
                self._after_solve = msgs[i + 1:]
                break
        return actions

    def _clock(self, clock: Clock) -> list[Action]:
        """The clock says how many days the run has. (An answer the DMO lost, restarting, needs nothing here: it
        had no receipt, so it is still being sent.)"""
        self.days = clock.days
        return []

    def _refused(self, refused: RefusedPayload) -> list[Action]:
        receipt, kind, seq = refused.receipt, refused.kind, refused.seq
        log.warning("%s: the DMO refused my %s #%d (%s): %s", self.name, kind, seq, receipt.code, receipt.reason)
        if kind == "registration" and receipt.code != "duplicate":
            raise AgentRefused(f"{self.name}: the DMO refused the registration ({receipt.code}): {receipt.reason}")
        return []

    def _operate(self, grid: GridState) -> list[Action]:
        if grid.subperiods != (self.award.subperiods if self.award else grid.subperiods):
            self.ignored["grid_state_wrong_subperiods"] += 1
            log.warning("%s: grid state with %d sub-periods, the award has %d; ignored", self.name, grid.subperiods,
                        self.award.subperiods)
            return []
        if self.operator is None:
            self._grid_seen[grid.hour] = grid
            log.warning("%s: grid state for hour %d before any award; no report", self.name, grid.hour)
            return []
        if grid.hour < self.operator.next_hour:
            self.ignored["grid_state_of_an_operated_hour"] += 1
            log.info("%s: grid state for hour %d again; already operated", self.name, grid.hour)
            return []
        if grid.hour > self.operator.next_hour:
            first = self.operator.next_hour
            self.operator.catch_up(grid.hour, {h: seen.connected for h, seen in self._grid_seen.items()})
            log.warning("%s: no grid state for hour(s) %d..%d: operated them unreported (the DMO settles them as "
                        "missing)", self.name, first, grid.hour - 1)
        room = self._room(grid)
        result = self.operator.operate_hour(grid.hour, grid.connected, room)
        if result.surplus.any():
            log.warning("%s: hour %d islanded: %.3f MWh of generation had nowhere to go and was let out "
                        '(docs/agent.md, "Feasibility")', self.name, grid.hour,
                        result.surplus.sum() / grid.subperiods)
        if result.envelope_infeasible:
            self.ignored["envelope_infeasible"] += 1
            log.warning("%s: hour %d cannot be operated within its operating envelope (%g MW below the award, %g "
                        "above): operated without it", self.name, grid.hour, room.export_mw, room.import_mw)
        if self.operator.next_hour > HOURS:
            self._realised_due = True
        return [Send(MeterReport(sender=self.name, market_day=self.market_day, hour=grid.hour,
                                 subperiods=grid.subperiods, p_m_mw=tuple(float(x) for x in result.p_m),
                                 deviation_mw=tuple(float(x) for x in result.deviation)))]

    def _room(self, grid: GridState) -> Room | None:
        """The rooms the grid state's operating envelope gives this microgrid's bus (docs/network.md, "Operating
        envelopes"): the bus its award names, else the one it registered at. None: the grid state carries no envelope
        (the copper plate), or none for that bus."""
        bus = self.award.bus if self.award.bus is not None else self.config.bus
        if bus is None or bus not in grid.buses:
            return None
        j = grid.buses.index(bus)
        return Room(grid.import_room_mw[j], grid.export_room_mw[j])

    def _handled(self, handled: Handled) -> list[Action]:
        """The computation of the message just handled counts in its day. After the last grid state of a day operated
        to its end (whose computation the agent_day carries), the agent_day follows the last meter report's receipt."""
        self._counted_in.append(handled.compute)
        if not self._realised_due:
            return []
        self._realised_due = False
        return [AwaitReceipts(), Send(self._realised(handled.counts))]

    def _realised(self, counts: MessageCounts) -> AgentDay:
        """The operated day as the agent alone knows it (docs/protocol.md, ``agent_day``): its own cost by term ($),
        the load it curtailed and the import above its award (MWh), its state at midnight, the computation of the
        day's messages handled so far and its message counts. The DMO records it and settles nothing by it."""
        day, midnight = self.operator.day_result(), self.operator.midnight()
        dispatch, k = day.schedule.dispatch, day.schedule.subperiods
        cost = day.cost
        msg = AgentDay(
            sender=self.name, market_day=self.market_day, generation=cost.generation, startup=cost.startup,
            curtailment=cost.curtailment, penalty=cost.penalty, total=cost.total,
            curtailment_mwh=float(dispatch.load_shed.sum()) / k, deviation_mwh=float(dispatch.dp_plus.sum()) / k,
            units={u.name: MidnightUnit(on=on, output_mw=out, hours=h) for u, on, out, h in
                   zip(self.case.units, midnight.unit_on, midnight.unit_output_mw, midnight.unit_hours)},
            stored_mwh=midnight.stored_mwh, compute=tuple(self.compute[:MAX_HANDLED]),
            messages=counts.model_copy(update={"ignored": dict(self.ignored)}))
        log.info("%s realised day %d: own cost $%.2f, curtailed %.3f MWh", self.name, self.day, cost.total,
                 msg.curtailment_mwh)
        return msg

    def _end_day(self) -> list[Action]:
        """The day is over (its summary and statement came, or the statement never will): the strategy learns it,
        then the next day begins, with the messages that came early for it handled at once, or the run is done."""
        self._observe()
        if self.day >= self.days:
            self.done = True
            return []
        self._next_day()
        ahead, self._ahead = self._ahead, []
        if ahead:  # the message that ended the day took their computation with it: it counts in the new day
            self._counted_in = self.compute
        return self._in_order(ahead)

    def _observe(self) -> None:
        """Tell the strategy what the day brought; one that fails to listen is said in one line, and bids on."""
        try:
            self.strategy.observe(DayLearned(self.day, self.market_day, self._bid_hours, self.award,
                                             self.statement, self.summary))
        except StrategyError as err:
            log.warning("%s: %s", self.name, err)

    def _next_day(self) -> None:
        """Carry the microgrid across midnight: the next day's case starts where the realised operation ended."""
        done = self.operator is not None and self.operator.next_hour > HOURS
        case = self._day_case(self.base, self.day + 1)
        if done:
            midnight = self.operator.midnight()
            log.info("%s: day %d starts from midnight: units on %s, storage %s MWh", self.name, self.day + 1,
                     [u.name for u, on in zip(self.case.units, midnight.unit_on) if on], midnight.stored_mwh)
            case = carry_over(case, midnight, name=f"{self.base.name}-day{self.day + 1}")
        else:
            log.warning("%s: day %d was not operated to its end: day %d starts from the case's initial state",
                        self.name, self.day, self.day + 1)
        self.day += 1
        self.market_day = market_days(self.market_day, 2)[1]
        self.case = case
        self._start_day()
        log.info("%s: day %d of %d, %s", self.name, self.day, self.days, self.market_day)


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
