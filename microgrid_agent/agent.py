"""A microgrid agent's market day over a Bus: register, bid, schedule against the award, operate hour by hour.

Zenoh's callback threads only enqueue what arrives; the agent handles it in order on its main thread, so a long
solve delays, but never reorders or drops, what comes next. The agent ends with the DMO's day summary, or when
it hears nothing for ``idle_s``.
"""

from __future__ import annotations

import json
import logging
import queue
import time
from dataclasses import dataclass

import numpy as np

from messages import Award, Bid, BidStep, CallForBids, DaySummary, GridState, MeterReport, Registration
from messages import Schedule as ScheduleMsg
from messages import SettlementStatement
from messages.transport import Bus
from scenarios.case import Case
from scenarios.generation import make_scenarios, sample

from .bidding import bid_curve, forecast_scenario
from .metrics import first_stage_of
from .model import Params
from .realtime import Operator
from .solve import solve

log = logging.getLogger("dmosim.agent")


@dataclass(frozen=True)
class AgentConfig:
    """How the agent schedules: scenarios of its stochastic model, islanding hours it plans for, solver gap and
    time limit, and the seed of its own scenarios (``seed``) and of the day it will actually live (``seed + 1000``)."""

    scenarios: int = 5
    island_hours: int = 1
    gap: float = 0.01
    time_limit: float = 600.0
    seed: int = 0
    idle_s: float = 3600.0


class AgentTimeout(RuntimeError):
    pass


class MicrogridAgent:
    def __init__(self, bus: Bus, case: Case, config: AgentConfig, market_day: str):
        self.bus, self.case, self.config, self.market_day = bus, case, config, market_day
        self.events: queue.Queue = queue.Queue()
        self.operator: Operator | None = None
        self.award: Award | None = None
        self.statement: SettlementStatement | None = None
        self.summary: DaySummary | None = None
        self.compute: list[dict] = []  # per message handled: kind, hour, wall_s, cpu_s (read by dmosim bench day)
        self._answering: tuple[float, float] | None = None  # perf_counter, process_time as the answer went out

    @property
    def id(self) -> str:
        return self.bus.name

    def run(self) -> DaySummary:
        k = self.bus.keys
        put = lambda key, msg, t: self.events.put(msg)  # noqa: E731
        for pattern in (k.call_for_bids(), k.award(self.id), k.grid(), k.statement(self.id), k.summary()):
            self.bus.subscribe(pattern, put)
        self.bus.wait_for_subscribers(k.register(self.id), self.config.idle_s)
        grid = self.case.grid
        self.bus.publish(Registration(sender=self.id, market_day=self.market_day, case=self.case.name,
                                      max_import_mw=grid.p_m_max, max_export_mw=grid.p_m_max))
        log.info("%s registered", self.id)
        while self.summary is None:
            try:
                msg = self.events.get(timeout=self.config.idle_s)
            except queue.Empty:
                raise AgentTimeout(f"{self.id}: nothing from the DMO for {self.config.idle_s:g} s") from None
            started, self._answering = (time.perf_counter(), time.process_time()), None
            self._handle(msg)
            ended = self._answering or (time.perf_counter(), time.process_time())
            self.compute.append({"kind": msg.kind, "hour": getattr(msg, "hour", None),
                                 "wall_s": ended[0] - started[0], "cpu_s": ended[1] - started[1]})
        # One line, so a benchmark can split the day's wall time into the agents' computation and the rest.
        log.info("%s compute %s", self.id, json.dumps(self.compute, separators=(",", ":")))
        return self.summary

    def _answer(self, msg) -> None:
        """Publish the answer to the message being handled. Its computation ends as it goes out: sending it is the
        protocol's work, and what the handler does afterwards overlaps the DMO's next step."""
        self._answering = time.perf_counter(), time.process_time()
        self.bus.publish(msg)

    def _handle(self, msg) -> None:
        if msg.market_day != self.market_day:
            log.warning("%s: ignoring %s for market day %s", self.id, msg.kind, msg.market_day)
        elif isinstance(msg, CallForBids):
            self._bid(msg)
        elif isinstance(msg, Award):
            self._schedule(msg)
        elif isinstance(msg, GridState):
            self._operate(msg)
        elif isinstance(msg, SettlementStatement):
            self.statement = msg
            log.info("%s statement: total $%.2f (penalty $%.2f)", self.id, msg.total, msg.deviation_penalty)
        elif isinstance(msg, DaySummary):
            self.summary = msg

    def _bid(self, call: CallForBids) -> None:
        curve = bid_curve(self.case, np.asarray(call.iso_price_per_mwh), seed=self.config.seed, gap=self.config.gap)
        hours = tuple(tuple(BidStep(price_per_mwh=float(s.price), quantity_mw=float(s.quantity)) for s in hour)
                      for hour in curve)
        self._answer(Bid(sender=self.id, market_day=self.market_day, hours=hours))
        log.info("%s bid sent", self.id)

    def _schedule(self, award: Award) -> None:
        """The stochastic schedule of the paper against the award (objective (1), constraints (2)-(21))."""
        self.award = award
        c, k = self.config, award.subperiods
        scen = make_scenarios(self.case, c.scenarios, k, c.island_hours, seed=c.seed)
        p_sch = np.asarray(award.p_sch_mw, float)
        schedule = solve(self.case, scen, Params(p_sch, award.penalty_per_mwh), gap=c.gap, time_limit=c.time_limit)
        realised = sample(self.case, 1, k, island_hours=0, seed=c.seed + 1000)
        self.operator = Operator(self.case, first_stage_of(schedule), p_sch, award.penalty_per_mwh, k, realised,
                                 forecast_scenario(self.case, k))
        p_m_hourly = (schedule.probability @ schedule.dispatch.p_m).reshape(24, k).mean(axis=1)
        self._answer(ScheduleMsg(
            sender=self.id, market_day=self.market_day, status=schedule.status,
            commitment={n: tuple(int(x) for x in schedule.commitment[n]) for n in schedule.unit_names},
            expected_cost=float(schedule.objective), p_m_expected_mw=tuple(float(x) for x in p_m_hourly),
            scenarios=schedule.scenarios, mip_gap=float(schedule.mip_gap)))
        log.info("%s scheduled: expected cost $%.2f, gap %.3f%%", self.id, schedule.objective, 100 * schedule.mip_gap)

    def _operate(self, grid: GridState) -> None:
        if self.operator is None:
            log.warning("%s: grid state for hour %d before any award; no report", self.id, grid.hour)
            return
        result = self.operator.operate_hour(grid.hour, grid.connected)
        self._answer(MeterReport(sender=self.id, market_day=self.market_day, hour=grid.hour,
                                 subperiods=grid.subperiods, p_m_mw=tuple(float(x) for x in result.p_m),
                                 deviation_mw=tuple(float(x) for x in result.deviation)))
