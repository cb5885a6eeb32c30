"""The messages the DMO publishes, built from its configuration and state: pure functions, one per kind.

Hours are 0..23 inside the DMO (settlement lines, meter hour indices) and 1..24 on the wire.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from messages import (DMO, AgentTotals, Award, CallForBids, Clock, DaySummary, GridState, Incident, SettlementStatement,
                      StatementLine)

from ..market.clearing import ClearingResult
from ..market.settlement import RULES_VERSION, Statement
from .config import DayConfig

if TYPE_CHECKING:  # the feeder's clearing loads scipy's LP, which a reader of recordings never needs
    from ..market.distflow import NetworkClearing
    from ..market.envelope import Rooms


def clock(config: DayConfig, day: int, phase: str, hour: int | None, deadline_s: float) -> Clock:
    return Clock(sender=DMO, market_day=config.market_day_of(day), phase=phase, hour=hour, deadline_s=deadline_s,
                 day=day, days=config.days)


def call_for_bids(config: DayConfig, day: int, deadline_s: float) -> CallForBids:
    """Day ``day``'s terms; bids are due ``deadline_s`` after it is sent."""
    c = config
    penalty, credit = c.rates
    return CallForBids(sender=DMO, market_day=c.market_day_of(day), iso_price_per_mwh=c.iso_price,
                       price_floor_per_mwh=c.price_floor, price_cap_per_mwh=c.price_cap,
                       import_limit_mw=c.import_limit, export_limit_mw=c.export_limit, penalty_per_mwh=penalty,
                       credit_per_mwh=credit, subperiods=c.subperiods, deadline_s=deadline_s)


def award(config: DayConfig, day: int, clearing: ClearingResult | NetworkClearing, agent: str,
          bus: str | None = None) -> Award:
    """One agent's award of day ``day``: its P_sch, its clearing prices (on a feeder, ``bus`` given, those of its bus
    with their components) and the congestion, and the settlement terms and rules."""
    c = config
    rule, (penalty, credit) = c.rule, c.rates
    price = tuple(clearing.agent_price[agent])
    feeder = {}
    if bus is not None:
        b = c.network.index[bus]
        feeder = dict(bus=bus, energy_price_per_mwh=tuple(clearing.energy.tolist()),
                      loss_price_per_mwh=tuple(clearing.loss[:, b].tolist()),
                      congestion_price_per_mwh=tuple(clearing.congestion[:, b].tolist()),
                      voltage_price_per_mwh=tuple(clearing.voltage[:, b].tolist()))
    return Award(sender=DMO, market_day=c.market_day_of(day), agent=agent, p_sch_mw=clearing.awards[agent],
                 clearing_price_per_mwh=price, penalty_per_mwh=penalty, credit_per_mwh=credit,
                 subperiods=c.subperiods, rules_version=RULES_VERSION, rules=rule.words, settlement_rule=rule.label,
                 deviation_cost=rule.deviation_cost(clearing.awards[agent], price),
                 congestion=clearing.congested, **feeder)


def grid_state(config: DayConfig, day: int, hour: int, rooms: Rooms | None = None) -> GridState:
    """Hour ``hour`` (1..24) of day ``day`` as realised: islanded in every sub-period of an islanded hour; on a
    feeder (``rooms``: the day's operating envelope), the hour's import and export rooms at every bus, whether or not
    the hour is islanded (P_M is 0 there whatever the rooms)."""
    connected = hour not in config.islanded(day)
    envelope = {} if rooms is None else dict(buses=config.network.buses,
                                              import_room_mw=tuple(rooms.import_mw[hour - 1].tolist()),
                                              export_room_mw=tuple(rooms.export_mw[hour - 1].tolist()))
    return GridState(sender=DMO, market_day=config.market_day_of(day), hour=hour, subperiods=config.subperiods,
                     connected=(connected,) * config.subperiods, **envelope)


def statement_message(st: Statement, market_day: str, penalty: float, credit: float,
                      rule: str | None = None) -> SettlementStatement:
    """A settlement Statement as the message the DMO publishes (hours 1..24 on the wire), settled by ``rule`` (its
    full name; None: the paper rule at ``penalty`` and ``credit``)."""
    lines = tuple(StatementLine(hour=line.hour + 1, p_sch_mw=line.award_mwh, clearing_price_per_mwh=line.price,
                                energy_charge=float(line.energy_charge), import_mwh=line.import_mwh,
                                deviation_mwh=line.deviation_mwh, under_import_mwh=line.under_import_mwh,
                                deviation_penalty=float(line.penalty), deviation_credit=float(line.credit),
                                total=float(line.total), missing=line.missing,
                                missing_subperiods=line.missing_subperiods) for line in st.lines)
    return SettlementStatement(sender=DMO, market_day=market_day, agent=st.agent, penalty_per_mwh=penalty,
                               credit_per_mwh=credit, rules_version=RULES_VERSION, settlement_rule=rule, lines=lines,
                               energy_charge=float(st.energy_charge), deviation_penalty=float(st.deviation_penalty),
                               deviation_credit=float(st.credit), total=float(st.total),
                               missing_subperiods=st.missing_subperiods)


def totals(st: Statement) -> AgentTotals:
    """An agent's line of the day summary: its statement's totals."""
    return AgentTotals(energy_charge=float(st.energy_charge), deviation_penalty=float(st.deviation_penalty),
                       deviation_credit=float(st.credit), total=float(st.total))


def day_summary(market_day: str, agents, prices, statements: dict[str, Statement], rejected: int,
                incidents: list[Incident] | tuple[Incident, ...]) -> DaySummary:
    """The day's outcome, sent once every statement is out: each agent's totals, the prices and the incidents."""
    return DaySummary(sender=DMO, market_day=market_day, agents=tuple(sorted(agents)), clearing_price_per_mwh=prices,
                      totals={a: totals(st) for a, st in statements.items()}, rejected_messages=rejected,
                      incidents=tuple(incidents))
