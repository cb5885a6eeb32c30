"""Settlement of a market day: an itemised statement per microgrid and the day's totals (docs/market.md).

Pure and exact. Every input number is taken at its shortest decimal form (Python ``repr``, which is what the
JSON recording carries) and computed on as an exact fraction; each money line item of a statement is rounded
once, half-even to the cent, and every total is the sum of rounded lines. So anyone who reads the recorded
numbers re-settles to the cent, with no dependence on float summation order. docs/market.md states the rules,
including the one for missing meter data and the proof that it never makes missing data cheaper.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from decimal import Decimal
from fractions import Fraction

from messages.schemas import GridState, Registration
from scenarios.horizon import HOURS, hourly

from .money import dollars, exact, exact_amount, money_sum, to_cents
from .rules import BUILT_IN, Charges, DeviationRule, GridHour, Meter, Rule, SettlementDay

# The version of the statement's form, announced in every award: a recording names it, and ``dmosim settle``
# refuses a version it does not implement. The rule itself is named beside it (docs/settlement.md).
RULES_VERSION = 1
# A reading may pass a registered limit by this much (MW), and read this far from 0 while islanded: float noise,
# not energy. The one tolerance by which the DMO accepts a meter report (acceptance.py) and settlement reads it.
READING_TOLERANCE_MW = 1e-9
RULES = ("energy charge = clearing price x award per hour; penalty = c x max(P_M - P_sch, 0) x dt per sub-period; "
         "under-import credited at the credit rate (default 0); a missing sub-period is settled at P_M = the "
         "agent's registered max import with no credit (docs/market.md)")


# --- statements -------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class HourLine:
    """One hour (index 0..23) of a statement. Energies in MWh, price in $/MWh, money in $ (Decimal cents).

    ``import_mwh`` is the settled import: metered sub-periods as reported, missing ones at p_m_max.
    ``deviation_mwh`` is the positive part of (P_M - P_sch) dt summed over sub-periods, ``under_import_mwh``
    the positive part of (P_sch - P_M) dt over metered sub-periods only. total = energy_charge + penalty - credit.
    """

    hour: int
    award_mwh: float
    price: float
    energy_charge: Decimal
    import_mwh: float
    deviation_mwh: float
    under_import_mwh: float
    penalty: Decimal
    credit: Decimal
    missing: bool
    missing_subperiods: int
    total: Decimal


@dataclass(frozen=True)
class Statement:
    """A microgrid's day: 24 hour lines and totals, each total the sum of its (rounded) lines."""

    agent: str
    lines: tuple[HourLine, ...]
    energy_charge: Decimal
    deviation_penalty: Decimal
    credit: Decimal
    total: Decimal
    missing_subperiods: int

    def as_dict(self) -> dict:
        """JSON-ready form: money as floats of whole cents (their repr is the exact cent amount)."""
        return {"agent": self.agent, "energy_charge": float(self.energy_charge),
                "deviation_penalty": float(self.deviation_penalty), "credit": float(self.credit),
                "total": float(self.total), "missing_subperiods": self.missing_subperiods,
                "lines": [_line_dict(line) for line in self.lines]}


def _line_dict(line: HourLine) -> dict:
    return {k: float(v) if isinstance(v, Decimal) else v for k, v in line.__dict__.items()}


@dataclass(frozen=True)
class DayTotals:
    """Totals over all agents' statements ($, MWh), and which agents sent no meter data at all."""

    agents: tuple[str, ...]
    energy_charge: Decimal
    deviation_penalty: Decimal
    credit: Decimal
    total: Decimal
    deviation_mwh: float
    missing_subperiods: int
    agents_without_meter: tuple[str, ...]

    def as_dict(self) -> dict:
        return {k: float(v) if isinstance(v, Decimal) else (list(v) if isinstance(v, tuple) else v)
                for k, v in self.__dict__.items()}


# --- one hour ---------------------------------------------------------------------------------------------

class RuleError(ValueError):
    """A settlement rule that raised, or returned what cannot be settled: one line naming the rule and the problem."""


def hour_line(day: SettlementDay, agent: str, hour: int, charges: Charges) -> HourLine:
    """One agent-hour (index 0..23): the rule's money, each item rounded once to the cent, beside the metered
    energies. ``import_mwh`` and ``deviation_mwh`` count a missing sub-period at the agent's max import."""
    readings = day.readings(agent, hour)
    p_sch, cap, dt = day.exact_awards[agent][hour], exact(day.max_import[agent]), day.dt
    metered = [exact(p) for p in readings if p is not None]
    n_missing = len(readings) - len(metered)
    imported = (sum(metered, Fraction(0)) + n_missing * cap) * dt
    over = (sum((max(p - p_sch, 0) for p in metered), Fraction(0)) + n_missing * max(cap - p_sch, 0)) * dt
    under = sum((max(p_sch - p, 0) for p in metered), Fraction(0)) * dt

    where = f"{agent} hour {hour + 1}"
    energy, penalty, credit = (to_cents(exact_amount(getattr(charges, name), f"{where}: {name}"))
                               for name in ("energy_charge", "penalty", "credit"))
    if penalty < 0 or credit < 0:
        raise RuleError(f"{where}: a negative {'penalty' if penalty < 0 else 'credit'}; a payment to the agent is a "
                        "credit, a charge a penalty")
    if charges.total is not None:
        total = to_cents(exact_amount(charges.total, f"{where}: total"))
        if total != energy + penalty - credit:
            raise RuleError(f"{where}: total {dollars(total)} is not energy_charge + penalty - credit "
                            f"({dollars(energy + penalty - credit)})")
    return HourLine(hour=hour, award_mwh=float(day.awards[agent][hour]), price=float(day.price_of(agent)[hour]),
                    energy_charge=dollars(energy), import_mwh=float(imported), deviation_mwh=float(over),
                    under_import_mwh=float(under), penalty=dollars(penalty), credit=dollars(credit),
                    missing=n_missing > 0, missing_subperiods=n_missing, total=dollars(energy + penalty - credit))


def statement(agent: str, lines: Sequence[HourLine]) -> Statement:
    """One agent's 24 hour lines and their totals."""
    lines = tuple(lines)
    return Statement(agent=agent, lines=lines,
                     energy_charge=money_sum(line.energy_charge for line in lines),
                     deviation_penalty=money_sum(line.penalty for line in lines),
                     credit=money_sum(line.credit for line in lines),
                     total=money_sum(line.total for line in lines),
                     missing_subperiods=sum(line.missing_subperiods for line in lines))


def day_totals(statements: Mapping[str, Statement], meter: Meter) -> DayTotals:
    agents = tuple(sorted(statements))
    s = [statements[a] for a in agents]
    deviation = sum((exact(line.deviation_mwh) for st in s for line in st.lines), Fraction(0))
    return DayTotals(agents=agents,
                      energy_charge=money_sum(st.energy_charge for st in s),
                      deviation_penalty=money_sum(st.deviation_penalty for st in s),
                      credit=money_sum(st.credit for st in s),
                      total=money_sum(st.total for st in s),
                      deviation_mwh=float(deviation),
                      missing_subperiods=sum(st.missing_subperiods for st in s),
                      agents_without_meter=tuple(a for a in agents if not meter.get(a)))


# --- validation and entry point ------------------------------------------------------------------------------

def _limits(name: str, value: float | Mapping[str, float], agents: Sequence[str]) -> dict[str, float]:
    if isinstance(value, Mapping):
        absent = [a for a in agents if a not in value]
        if absent:
            raise ValueError(f"no {name} for agent {absent[0]}")
    out = {a: value[a] if isinstance(value, Mapping) else value for a in agents}
    for agent, v in out.items():
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} of {agent} must be a finite number >= 0, got {v!r}")
    return out


def _check_meter(meter: Meter, day: SettlementDay) -> None:
    if not isinstance(meter, Mapping):
        raise ValueError("meter must map agent id to {hour index: readings}")
    for agent, hours in meter.items():
        if agent not in day.awards:
            raise ValueError(f"meter report from agent {agent!r}, which has no award")
        if not isinstance(hours, Mapping):
            raise ValueError(f"meter of {agent} must map hour index to readings")
        for h, readings in hours.items():
            if isinstance(h, bool) or not isinstance(h, numbers.Integral) or not 0 <= h < HOURS:
                raise ValueError(f"meter of {agent}: hour index must be an integer 0..{HOURS - 1}, got {h!r}")
            if isinstance(readings, (str, bytes)) or not isinstance(readings, Sequence):
                raise ValueError(f"meter of {agent}, hour index {h}: readings must be a sequence")
            if len(readings) != day.subperiods:
                raise ValueError(f"meter of {agent}, hour index {h}: {len(readings)} readings, "
                                 f"expected {day.subperiods}")
            for p in readings:
                if p is None:
                    continue
                if isinstance(p, bool) or not isinstance(p, numbers.Real) or not math.isfinite(p):
                    raise ValueError(f"meter of {agent}, hour index {h}: reading {p!r} is not a finite number")
                if p > day.max_import[agent] + READING_TOLERANCE_MW:
                    raise ValueError(f"meter of {agent}, hour index {h}: reading {p} MW above "
                                     f"p_m_max {day.max_import[agent]} MW")
                if p < -day.max_export[agent] - READING_TOLERANCE_MW:
                    raise ValueError(f"meter of {agent}, hour index {h}: reading {p} MW below -p_m_min "
                                     f"{day.max_export[agent]} MW")


def settlement_day(awards: Mapping[str, Sequence[float]], prices: Sequence[float], meter: Meter, *,
                   subperiods: int, p_m_max: float | Mapping[str, float],
                   p_m_min: float | Mapping[str, float] | None = None,
                   agent_prices: Mapping[str, Sequence[float]] | None = None,
                   grid: Sequence[GridHour] | None = None, bus: Mapping[str, str] | None = None) -> SettlementDay:
    """The day a rule settles, checked: ValueError with a one-line reason for invalid input (``settle``).
    ``agent_prices`` (agent -> 24 $/MWh, on a feeder: each agent's bus price) settles each agent's energy at its
    own prices; without it every agent's are ``prices``. ``grid``: the 24 hours' grid states (None: not known);
    ``bus``: agent -> its bus on a feeder."""
    if not isinstance(awards, Mapping):
        raise ValueError("awards must map agent id to 24 hourly MW values")
    agents = sorted(awards)
    for a in agents:
        if not isinstance(a, str) or not a.strip():
            raise ValueError(f"agent id must be a non-empty string, got {a!r}")
    if isinstance(subperiods, bool) or not isinstance(subperiods, int) or subperiods < 1:
        raise ValueError(f"subperiods must be an integer >= 1, got {subperiods!r}")
    max_import = _limits("p_m_max", p_m_max, agents)
    day = SettlementDay(awards={a: hourly(awards[a], f"award of {a}") for a in agents},
                        prices=hourly(prices, "clearing price"), meter=meter, subperiods=subperiods,
                        max_import=max_import,
                        max_export=max_import if p_m_min is None else _limits("p_m_min", p_m_min, agents),
                        agent_prices=None if agent_prices is None else _agent_prices(agent_prices, agents),
                        grid=None if grid is None else _grid(grid, subperiods), bus=dict(bus or {}))
    _check_meter(meter, day)
    return day


def _grid(grid: Sequence[GridHour], subperiods: int) -> tuple[GridHour, ...]:
    grid = tuple(grid)
    if len(grid) != HOURS or not all(isinstance(g, GridHour) for g in grid):
        raise ValueError(f"grid must be {HOURS} GridHours, one per hour")
    for h, g in enumerate(grid):
        if len(g.connected) != subperiods:
            raise ValueError(f"grid state of hour index {h}: {len(g.connected)} sub-periods, expected {subperiods}")
    return grid


def grid_hours(states: Sequence[GridState] | None) -> tuple[GridHour, ...] | None:
    """The DMO's 24 grid_state messages (hours 1..24, in order) as the ``grid`` a rule reads; None stays None."""
    if states is None:
        return None
    return tuple(GridHour(connected=tuple(g.connected), buses=tuple(g.buses), import_room_mw=tuple(g.import_room_mw),
                          export_room_mw=tuple(g.export_room_mw)) for g in states)


def _agent_prices(agent_prices, agents: list[str]) -> dict[str, tuple[float, ...]]:
    if not isinstance(agent_prices, Mapping) or set(agent_prices) != set(agents):
        raise ValueError("agent prices must map each awarded agent, and only those, to 24 hourly prices")
    return {a: hourly(agent_prices[a], f"price of {a}") for a in agents}


def accepted_day(awards: Mapping[str, Sequence[float]], prices: Sequence[float], meter: Meter, *, subperiods: int,
                 registered: Mapping[str, Registration],
                 agent_prices: Mapping[str, Sequence[float]] | None = None,
                 grid: Sequence[GridState] | None = None, bus: Mapping[str, str] | None = None) -> SettlementDay:
    """The day the DMO settles, from what it accepted: each awarded agent's P_sch (MW) and the clearing prices, the
    meter reports it took (agent -> {hour index 0..23: K readings}; an absent hour is missing) and each agent's
    registration, whose limits bound its readings and price its missing sub-periods. The live DMO
    (operator/machine.py), re-settlement (replay/resettle.py) and the replayed DMO (replay/recorded.py) all settle this
    day, so a recorded day re-settles identically. On a feeder, ``prices`` are the substation's and
    ``agent_prices`` each agent's bus prices, its award's clearing prices, and ``bus`` each agent's bus. ``grid`` is
    the 24 grid_state messages the DMO published (None where a recording lacks them), which a rule reads as
    ``SettlementDay.grid``."""
    return settlement_day(awards, prices, meter, subperiods=subperiods,
                          p_m_max={a: r.max_import_mw for a, r in registered.items()},
                          p_m_min={a: r.max_export_mw for a, r in registered.items()}, agent_prices=agent_prices,
                          grid=grid_hours(grid), bus=bus)


def settle_day(day: SettlementDay, rule: Rule, name: str, **params) -> tuple[dict[str, Statement], DayTotals]:
    """Settle ``day`` under ``rule`` (called ``name`` in errors) with ``params``; RuleError, one line, if the rule
    raises or returns what cannot be settled."""
    try:
        charges = rule(day, **params)
    except ValueError as err:
        raise RuleError(f"settlement rule {name}: {err}") from None
    except Exception as err:  # a user's rule may raise anything: say what and where, in one line
        raise RuleError(f"settlement rule {name} raised {type(err).__name__}: {err}") from None
    if not isinstance(charges, Mapping) or set(charges) != set(day.awards):
        got = sorted(charges) if isinstance(charges, Mapping) else type(charges).__name__
        raise RuleError(f"settlement rule {name} returned {got}; it must map each awarded agent "
                        f"({', '.join(sorted(day.awards))}) to 24 Charges")
    statements = {}
    for agent in sorted(day.awards):
        hours = charges[agent]
        if isinstance(hours, (str, bytes)) or not isinstance(hours, Sequence) or len(hours) != HOURS:
            raise RuleError(f"settlement rule {name}: {agent} must have 24 Charges, one per hour")
        if not all(isinstance(c, Charges) for c in hours):
            raise RuleError(f"settlement rule {name}: {agent}'s hours must be Charges")
        try:
            statements[agent] = statement(agent, [hour_line(day, agent, h, c) for h, c in enumerate(hours)])
        except ValueError as err:
            raise RuleError(f"settlement rule {name}: {err}") from None
    return statements, day_totals(statements, day.meter)


def settle(awards: Mapping[str, Sequence[float]], prices: Sequence[float], meter: Meter, *, subperiods: int,
           p_m_max: float | Mapping[str, float], p_m_min: float | Mapping[str, float] | None = None,
           rule: Rule | None = None, **params) -> tuple[dict[str, Statement], DayTotals]:
    """Settle a market day: one statement per awarded agent (sorted by id) and the day's totals.

    ``awards``: agent -> 24 MW (P_sch, + import); ``prices``: 24 clearing prices ($/MWh); ``meter``: agent ->
    {hour index 0..23: K readings of P_M (MW), None for a missing sub-period}; an absent hour or agent is
    missing. ``p_m_max`` and ``p_m_min`` (MW, scalar or per agent; ``p_m_min`` defaults to ``p_m_max``) are the
    most an agent can import and export: readings beyond them are rejected. ``rule`` is a settlement rule
    (default: the paper's, ``rules.BUILT_IN["paper"]``) and ``params`` its parameters, e.g. ``penalty=150``.
    Raises ValueError with a one-line reason for invalid input (RuleError for what the rule does).
    """
    day = settlement_day(awards, prices, meter, subperiods=subperiods, p_m_max=p_m_max, p_m_min=p_m_min)
    rule = rule or BUILT_IN["paper"]
    if isinstance(rule, DeviationRule):
        rule.parameters(params)  # an invalid parameter of a built-in rule is bad input, not a rule that fails
    return settle_day(day, rule, getattr(rule, "name", getattr(rule, "__name__", "rule")), **params)
