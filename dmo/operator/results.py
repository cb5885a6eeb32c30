"""What a run of the DMO gives: each settled day, and the run's days together, as the JSON of ``dmosim run --json``
(docs/experiments.md, "The result")."""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field

from messages import Schedule

from scenarios.horizon import HOURS

from ..market.clearing import ClearingResult
from ..market.settlement import DayTotals, Statement
from .report import AgentSettlement, DatedIncident, DayReport, DmoReport, ReportedDay, SettledTotals, StoppedShort
from .state import DayState


def stopped_short(schedules: Mapping[str, Schedule]) -> list[StoppedShort]:
    """The day's schedules whose solve stopped short of its gap (any status but "optimal": a time limit, most
    often), by agent: its ``agent``, ``status`` and certified ``mip_gap`` (None where the solve certified none)."""
    return [StoppedShort(agent=a, status=m.status, mip_gap=m.mip_gap) for a, m in sorted(schedules.items())
            if m.stopped_short]


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

    def report(self) -> DayReport:
        """The day as its part of the run's result: prices, awards, each agent's settlement, incidents and counts."""
        s = self.state
        return DayReport(
            day=self.day, market_day=self.market_day, islanded_hours=list(self.islanded_hours),
            clearing_prices=list(self.clearing.price), congestion=list(self.clearing.congested),
            awards={a: list(v) for a, v in self.clearing.awards.items()},
            settlement={a: AgentSettlement(energy_charge=float(st.energy_charge),
                                           deviation_penalty=float(st.deviation_penalty),
                                           credit=float(st.credit), total=float(st.total),
                                           award_mwh=sum(line.award_mwh for line in st.lines),
                                           import_mwh=sum(line.import_mwh for line in st.lines),
                                           deviation_mwh=sum(line.deviation_mwh for line in st.lines),
                                           missing_subperiods=st.missing_subperiods)
                        for a, st in self.statements.items()},
            day_summary=SettledTotals.model_validate(self.totals.as_dict()),
            expected_cost={a: m.expected_cost for a, m in s.schedules.items()},
            schedules_stopped_short=stopped_short(s.schedules),
            rejected_messages=s.rejected, rejected_by_code=dict(s.rejected_by_code),
            accepted_messages=dict(s.accepted), received_again=s.again, dropped_messages=dict(s.dropped),
            locked_out=list(self.locked_out), incidents=list(s.incidents), phase_s=self.phase_s)


@dataclass(frozen=True)
class RunResult:
    """Every day of a run, in order, as its report (``DayResult.report``), and the last day's whole result (its
    state and statements). The DMO keeps the days it has settled, and the realised days, on disk as the run goes
    (finished.py): they come back here when the run ends."""

    days: list[DayReport]
    settlement_rule: str  # the rule every day was settled by, with every parameter
    agents: list[str]  # the agents registered
    # agent -> market day -> its agent_day as reported, without the envelope (finished.py)
    realised: dict[str, dict[str, dict]] = field(default_factory=dict)
    last: DayResult | None = None  # the last day's whole result

    def report(self, run_id: str, transport: dict) -> DmoReport:
        """The DMO's part of the ``dmosim run --json`` object (docs/experiments.md, "The result"). A one-day run
        gives that day's fields at the top; a longer one gives the run's: hourly values concatenated day after day,
        each agent's settlement summed, incidents of every day (each with its market day), and ``islanded_hours``
        per day. ``days`` holds each day's own object either way."""
        days, agents = self.days, self.agents
        out = {"run_id": run_id, "agents": agents, "days": days, "settlement_rule": self.settlement_rule,
               "transport": transport, "realised": self.realised_days(agents)}
        if len(days) == 1:
            return DmoReport.model_validate({**out, **days[0].model_dump(), "days": days})
        money = ("energy_charge", "deviation_penalty", "credit", "total")
        settlement = {a: AgentSettlement.model_validate({
            k: (round(sum(getattr(d.settlement[a], k) for d in days), 2) if k in money
                else sum(getattr(d.settlement[a], k) for d in days)) for k in AgentSettlement.model_fields})
            for a in days[0].settlement}
        return DmoReport(
            **out, market_day=days[0].market_day, market_days=[d.market_day for d in days],
            islanded_hours=[d.islanded_hours for d in days],
            clearing_prices=[p for d in days for p in d.clearing_prices],
            congestion=[c for d in days for c in d.congestion],
            awards={a: [x for d in days for x in d.awards.get(a, [0.0] * HOURS)] for a in agents},
            settlement=settlement,
            rejected_messages=sum(d.rejected_messages for d in days),
            rejected_by_code=dict(sum((Counter(d.rejected_by_code) for d in days), Counter())),
            accepted_messages=dict(sum((Counter(d.accepted_messages) for d in days), Counter())),
            received_again=sum(d.received_again for d in days),
            dropped_messages=dict(sum((Counter(d.dropped_messages) for d in days), Counter())),
            locked_out=sorted({a for d in days for a in d.locked_out}),
            incidents=[DatedIncident(**i.model_dump(), market_day=d.market_day) for d in days for i in d.incidents],
            schedules_stopped_short=[x.model_copy(update={"market_day": d.market_day}) for d in days
                                     for x in d.schedules_stopped_short])

    def realised_days(self, agents: list[str]) -> dict[str, list[ReportedDay]]:
        """Agent -> the realised days it reported (its ``agent_day`` messages, as received), in order of the day,
        each with the run's ``day`` and its ``market_day``; an agent that reported none has an empty list."""
        day_of = {d.market_day: d.day for d in self.days}
        return {a: [ReportedDay.model_validate({"day": day_of.get(market_day), "market_day": market_day, **reported})
                    for market_day, reported in sorted(self.realised.get(a, {}).items())] for a in agents}
