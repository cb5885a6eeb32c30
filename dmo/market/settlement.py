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

from scenarios.horizon import HOURS, hourly

Meter = Mapping[str, Mapping[int, Sequence[float | None]]]

# The rules as the DMO announces them in every award, with their version: a recording names the rules it was
# settled by, and ``dmosim settle`` refuses a version it does not implement.
RULES_VERSION = 1
RULES = ("energy charge = clearing price x award per hour; penalty = c x max(P_M - P_sch, 0) x dt per sub-period; "
         "under-import credited at the credit rate (default 0); a missing sub-period is settled at P_M = the "
         "agent's registered max import with no credit (docs/market.md)")


# --- exact arithmetic ---------------------------------------------------------------------------------------

def exact(x: float) -> Fraction:
    """The exact value of x's shortest decimal form: 0.1 is 1/10, as written in the recording."""
    return Fraction(repr(float(x)))


def to_cents(amount: Fraction) -> int:
    """Round an exact amount ($) half-even to whole cents: the only rounding settlement does."""
    return int(round(amount * 100))


def dollars(cents: int) -> Decimal:
    return Decimal(cents).scaleb(-2)


def _money(amounts) -> Decimal:
    """Exact sum of cent amounts, kept at two places (an empty sum is 0.00)."""
    return sum(amounts, Decimal("0.00"))


# --- rules ------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Rules:
    """Settlement parameters. ``penalty`` c and ``credit`` in $/MWh, finite and >= 0; ``subperiods`` K per
    hour (dt = 1/K h); ``p_m_max`` (MW) per agent, the import assumed for every missing meter sub-period."""

    subperiods: int
    penalty: float
    credit: float
    p_m_max: Mapping[str, float]

    def __post_init__(self) -> None:
        if isinstance(self.subperiods, bool) or not isinstance(self.subperiods, int) or self.subperiods < 1:
            raise ValueError(f"subperiods must be an integer >= 1, got {self.subperiods!r}")
        for name in ("penalty", "credit"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or math.isnan(v):
                raise ValueError(f"{name} rate must be a number, got {v!r}")
            if math.isinf(v):
                raise ValueError(f"{name} rate must be finite to be settled, got {v}")
            if v < 0:
                raise ValueError(f"{name} rate must be >= 0, got {v}")
        for agent, v in self.p_m_max.items():
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v < 0:
                raise ValueError(f"p_m_max of {agent} must be a finite number >= 0, got {v!r}")


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

def hour_line(hour: int, award: float, price: float, readings: Sequence[float | None] | None,
              rules: Rules, p_m_max: float) -> HourLine:
    """Settle one agent-hour. ``readings`` holds P_M (MW) per sub-period, None for a missing sub-period;
    ``readings`` None means the whole hour is missing. A missing sub-period is settled at P_M = p_m_max, the
    most the agent could have imported, with no under-import credit (docs/market.md, "Missing meter data")."""
    k = rules.subperiods
    readings = [None] * k if readings is None else list(readings)
    p_sch, cap = exact(award), exact(p_m_max)
    metered = [exact(p) for p in readings if p is not None]
    n_missing = k - len(metered)
    dt = Fraction(1, k)

    imported = (sum(metered, Fraction(0)) + n_missing * cap) * dt
    over = (sum((max(p - p_sch, 0) for p in metered), Fraction(0)) + n_missing * max(cap - p_sch, 0)) * dt
    under = sum((max(p_sch - p, 0) for p in metered), Fraction(0)) * dt

    energy = to_cents(exact(price) * p_sch)  # MW x 1 h = MWh
    penalty = to_cents(exact(rules.penalty) * over)
    credit = to_cents(exact(rules.credit) * under)
    return HourLine(hour=hour, award_mwh=float(award), price=float(price), energy_charge=dollars(energy),
                    import_mwh=float(imported), deviation_mwh=float(over), under_import_mwh=float(under),
                    penalty=dollars(penalty), credit=dollars(credit), missing=n_missing > 0,
                    missing_subperiods=n_missing, total=dollars(energy + penalty - credit))


def statement(agent: str, award: Sequence[float], prices: Sequence[float],
              reports: Mapping[int, Sequence[float | None]], rules: Rules) -> Statement:
    """One agent's 24 hour lines and their totals."""
    lines = tuple(hour_line(h, award[h], prices[h], reports.get(h), rules, rules.p_m_max[agent])
                  for h in range(HOURS))
    return Statement(agent=agent, lines=lines,
                     energy_charge=_money(line.energy_charge for line in lines),
                     deviation_penalty=_money(line.penalty for line in lines),
                     credit=_money(line.credit for line in lines),
                     total=_money(line.total for line in lines),
                     missing_subperiods=sum(line.missing_subperiods for line in lines))


def day_totals(statements: Mapping[str, Statement], meter: Meter) -> DayTotals:
    agents = tuple(sorted(statements))
    s = [statements[a] for a in agents]
    deviation = sum((exact(line.deviation_mwh) for st in s for line in st.lines), Fraction(0))
    return DayTotals(agents=agents,
                      energy_charge=_money(st.energy_charge for st in s),
                      deviation_penalty=_money(st.deviation_penalty for st in s),
                      credit=_money(st.credit for st in s),
                      total=_money(st.total for st in s),
                      deviation_mwh=float(deviation),
                      missing_subperiods=sum(st.missing_subperiods for st in s),
                      agents_without_meter=tuple(a for a in agents if not meter.get(a)))


# --- validation and entry point ------------------------------------------------------------------------------

def _check_meter(meter: Meter, awards: Mapping[str, Sequence[float]], rules: Rules) -> None:
    if not isinstance(meter, Mapping):
        raise ValueError("meter must map agent id to {hour index: readings}")
    for agent, hours in meter.items():
        if agent not in awards:
            raise ValueError(f"meter report from agent {agent!r}, which has no award")
        if not isinstance(hours, Mapping):
            raise ValueError(f"meter of {agent} must map hour index to readings")
        for h, readings in hours.items():
            if isinstance(h, bool) or not isinstance(h, numbers.Integral) or not 0 <= h < HOURS:
                raise ValueError(f"meter of {agent}: hour index must be an integer 0..{HOURS - 1}, got {h!r}")
            if isinstance(readings, (str, bytes)) or not isinstance(readings, Sequence):
                raise ValueError(f"meter of {agent}, hour index {h}: readings must be a sequence")
            if len(readings) != rules.subperiods:
                raise ValueError(f"meter of {agent}, hour index {h}: {len(readings)} readings, "
                                 f"expected {rules.subperiods}")
            for p in readings:
                if p is None:
                    continue
                if isinstance(p, bool) or not isinstance(p, numbers.Real) or not math.isfinite(p):
                    raise ValueError(f"meter of {agent}, hour index {h}: reading {p!r} is not a finite number")
                if p > rules.p_m_max[agent]:
                    raise ValueError(f"meter of {agent}, hour index {h}: reading {p} MW above "
                                     f"p_m_max {rules.p_m_max[agent]} MW")


def settle(awards: Mapping[str, Sequence[float]], prices: Sequence[float], meter: Meter, *, subperiods: int,
           penalty: float, p_m_max: float | Mapping[str, float], credit: float = 0.0,
           ) -> tuple[dict[str, Statement], DayTotals]:
    """Settle a market day: one statement per awarded agent (sorted by id) and the day's totals.

    ``awards``: agent -> 24 MW (P_sch, + import); ``prices``: 24 clearing prices ($/MWh); ``meter``: agent ->
    {hour index 0..23: K readings of P_M (MW), None for a missing sub-period}; an absent hour or agent is
    missing. ``penalty`` c and ``credit`` in $/MWh, finite and >= 0; ``p_m_max`` (MW), scalar or per agent, the
    most an agent can import: readings above it are rejected, missing sub-periods are settled at it.
    Raises ValueError with a one-line reason for invalid input.
    """
    if not isinstance(awards, Mapping):
        raise ValueError("awards must map agent id to 24 hourly MW values")
    agents = sorted(awards)
    for a in agents:
        if not isinstance(a, str) or not a.strip():
            raise ValueError(f"agent id must be a non-empty string, got {a!r}")
    award_rows = {a: hourly(awards[a], f"award of {a}") for a in agents}
    price_row = hourly(prices, "clearing price")
    if isinstance(p_m_max, Mapping):
        absent = [a for a in agents if a not in p_m_max]
        if absent:
            raise ValueError(f"no p_m_max for agent {absent[0]}")
        caps = {a: p_m_max[a] for a in agents}
    else:
        caps = {a: p_m_max for a in agents}
    rules = Rules(subperiods=subperiods, penalty=penalty, credit=credit, p_m_max=caps)
    _check_meter(meter, awards, rules)

    statements = {a: statement(a, award_rows[a], price_row, meter.get(a, {}), rules) for a in agents}
    return statements, day_totals(statements, meter)
