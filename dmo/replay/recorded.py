"""A recorded day as the market the DMO's machine runs (``dmosim replay --as-dmo``): one live agent process takes part
in the day a recording holds, against its recorded terms, award and grid.

The DMO's machine (dmo/operator/machine.py), over Zenoh as the live DMO runs it (dmo/operator/day.py), sequences the
day, decides on what the agent sends by the live DMO's rules, receipts it and waits for it; this market gives the
recorded call for bids, the agent's recorded award and each hour's recorded grid state (its islanding and operating
envelope), and settles the agent's meter reports by the recorded rule at the recorded prices (the award's penalty,
credit and sub-periods, its registration's max import for missing data), as ``dmosim settle`` does. Only the agent
replayed may register, at the bus its award names.
"""

from __future__ import annotations

import json

from messages import Award, CallForBids, GridState, Message, Registration, SettlementStatement
from messages.recording import Recording
from scenarios.horizon import HOURS

from ..market.acceptance import out_of_phase
from ..market.choice import ChosenRule
from ..market.clearing import ClearingResult
from ..market.settlement import DayTotals, Statement, accepted_day
from ..operator.config import WALL, DayConfig
from ..operator.intake import Accept
from ..operator.results import RunResult
from ..operator.state import DayState
from .resettle import RecordedDay, as_message, day_messages


class RecordedMarket:
    """The recorded ``day`` of ``rec`` for ``agent`` alone, settled by ``rule`` (the recorded one, as the caller was
    allowed to load it). A day that lacks the call for bids or a grid state (a cut recording) is a ValueError."""

    def __init__(self, rec: Recording, day: RecordedDay, agent: str, rule: ChosenRule):
        self.day, self.agent, self.rule = day, agent, rule
        self.award_msg: Award = day.awards[agent]
        calls = [msg for _, msg in day_messages(rec, day.market_day, "call_for_bids")]
        grids: dict[int, GridState] = {}
        for _, msg in day_messages(rec, day.market_day, "grid_state"):
            grids.setdefault(msg.hour, msg)  # the DMO sends each hour's once (a copy is the same)
        missing = [h for h in range(1, HOURS + 1) if h not in grids]
        if not calls or missing:
            what = "no call for bids" if not calls else f"no grid state for hour(s) {_hours(missing)}"
            raise ValueError(f"{rec.path}: {day.market_day} has {what}"
                             + (f" ({rec.cut_note})" if rec.cut_note else "") + "; --as-dmo plays a whole day")
        self.call, self.grids = calls[0], [grids[h] for h in range(1, HOURS + 1)]

    def registration(self, state: DayState) -> Accept:
        def accept(msg):
            if not isinstance(msg, Registration):
                return out_of_phase(msg, state.phase)
            if msg.sender != self.agent:
                return "invalid", f"this is the recorded DMO of {self.agent} alone: {msg.sender} cannot take part"
            if msg.bus is not None and msg.bus != self.award_msg.bus:
                return "invalid", (f"{msg.sender} names bus {msg.bus}, but its recorded award is at "
                                   f"{self.award_msg.bus or 'no bus (a copper plate)'}")
            state.registered[msg.sender] = msg
            state.meter[msg.sender] = {}
            return None

        return accept

    def call_for_bids(self, day: int, deadline_s: float) -> CallForBids:
        return self.call

    def clear(self, state: DayState) -> ClearingResult:
        prices, _ = self.day.prices([self.agent])
        return ClearingResult(prices, {self.agent: self.award_msg.p_sch_mw}, self.award_msg.congestion)

    def award(self, state: DayState, clearing: ClearingResult, agent: str) -> Award:
        return self.award_msg

    def planned(self, state: DayState, clearing: ClearingResult) -> list[Message]:
        return []

    def grid_states(self, state: DayState, clearing: ClearingResult) -> list[GridState]:
        return self.grids

    def settle(self, state: DayState, clearing: ClearingResult) -> tuple[dict[str, Statement], DayTotals]:
        prices, own = self.day.prices([self.agent])
        return self.rule.settle(accepted_day(clearing.awards, prices, state.meter,
                                             subperiods=self.award_msg.subperiods, registered=state.registered,
                                             agent_prices=own, grid=self.grids,
                                             bus={} if self.award_msg.bus is None else {self.agent: self.award_msg.bus}))

    def statement(self, state: DayState, st: Statement) -> SettlementStatement:
        return as_message(self.day, st)

    def realised(self, state: DayState) -> list[Message]:
        return []


def replay_config(day: RecordedDay, timeout_s: float) -> DayConfig:
    """The replayed DMO's day: one agent, on the wall clock with every phase, hour and the lingering after the
    summary at most ``timeout_s`` (the agent may never come), the recorded terms."""
    terms = day.terms
    return DayConfig(market_day=day.market_day, agents=1, iso_price=terms.clearing_price_per_mwh,
                     import_limit=0.0, export_limit=0.0, penalty=terms.penalty_per_mwh, credit=terms.credit_per_mwh,
                     subperiods=terms.subperiods, islanded_hours=(), registration_s=timeout_s, bids_s=timeout_s,
                     schedule_s=timeout_s, hour_s=timeout_s, linger_s=timeout_s, clock=WALL)


def replay_result(run: RunResult, market: RecordedMarket, run_id: str) -> dict:
    """What ``dmosim replay --as-dmo --json`` prints: the agent's new statement against the recorded one, its meter
    reports, and the day's rejections and incidents."""
    day, agent, last = market.day, market.agent, run.last
    message = market.statement(last.state, last.statements[agent])
    recorded = day.statements.get(agent)
    state = last.state
    return {"run_id": run_id, "market_day": day.market_day, "agent": agent,
            "statement": json.loads(message.model_dump_json(exclude={"seq", "sent_at"})),
            "recorded_total": recorded.total if recorded else None,
            "difference": round(message.total - recorded.total, 2) if recorded else None,
            "meter_reports": len(state.meter.get(agent, {})), "rejected_messages": state.rejected,
            "incidents": [f"{i.phase}{f' hour {i.hour}' if i.hour else ''}: {i.reason}" for i in state.incidents]}


def render(result: dict) -> str:
    st = result["statement"]
    rows = [f"agent {result['agent']} against the recorded DMO of {result['market_day']} (run {result['run_id']})",
            f"{'hour':>4}{'award MW':>10}{'import MWh':>12}{'dev. MWh':>10}{'energy $':>11}{'penalty $':>11}{'total $':>11}"]
    for line in st["lines"]:
        rows.append(f"{line['hour']:>4}{line['p_sch_mw']:>10.3f}{line['import_mwh']:>12.3f}{line['deviation_mwh']:>10.3f}"
                    f"{line['energy_charge']:>11,.2f}{line['deviation_penalty']:>11,.2f}{line['total']:>11,.2f}"
                    + ("  missing" if line["missing"] else ""))
    rows.append(f"total: ${st['total']:,.2f} (energy ${st['energy_charge']:,.2f}, penalty ${st['deviation_penalty']:,.2f}, "
                f"credit ${st['deviation_credit']:,.2f}); {result['meter_reports']}/24 meter reports")
    if result["recorded_total"] is not None:
        rows.append(f"recorded agent's total: ${result['recorded_total']:,.2f}; difference ${result['difference']:+,.2f}")
    for incident in result["incidents"]:
        rows.append(f"incident: {incident}")
    if result.get("recording"):
        rows.append(f"recording: {result['recording']}")
    return "\n".join(rows)


def _hours(hours: list[int]) -> str:
    return ", ".join(map(str, hours[:5])) + (", ..." if len(hours) > 5 else "")
