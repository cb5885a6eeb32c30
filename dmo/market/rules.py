"""Settlement rules: how a day's deviations from the awards are priced (docs/settlement.md).

A rule is a pure function ``rule(day, **parameters)`` of a ``SettlementDay`` (awards, clearing prices, metered
sub-periods, registered limits) that returns, per agent, 24 hourly ``Charges`` (energy charge, penalty, credit and
optionally their total); what a missing sub-period costs is part of the rule. ``settlement.settle`` checks what a
rule returns and assembles the statements.

The built-in rules price the deviation d = P_M - P_sch of each sub-period by a piecewise-linear function of d
(``DeviationPrice``), fixed per hour: the paper's one-sided penalty c x max(d, 0) of objective (1) with an optional
credit below the award, a symmetric one, a dead band and a price-linked one. A convex function of that form is
what the agent's mismatch term (19)-(21) generalises to.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from functools import cached_property

from scenarios.horizon import HOURS

from .money import exact

Meter = Mapping[str, Mapping[int, Sequence[float | None]]]

# The ranges of the built-ins' parameters (docs/settlement.md, "Parameters and their ranges"). A rate ($/MWh) is at
# most 100 x the paper's value of lost load ($10,000/MWh): far above what makes an agent shed load rather than
# deviate, and small enough that the model's cost coefficients stay within what HiGHS's tolerances resolve. A MW
# quantity (a band) is at most 1,000,000 MW, above the largest fleet's ties together (1,024 agents x 160 MW).
# ``k`` times the DMO's price cap ($10,000/MWh) stays within MAX_RATE. A share is a fraction.
MAX_RATE = 1_000_000.0
MAX_MW = 1_000_000.0
MAX_PRICE_FACTOR = 100.0


@dataclass(frozen=True)
class GridHour:
    """One hour's grid state as the DMO published it (its ``grid_state`` message): ``connected`` K booleans, one per
    sub-period, False where the grid islanded the microgrids (U = 0, P_M = 0); on a feeder the hour's operating
    envelope, ``import_room_mw`` and ``export_room_mw`` (MW) at each bus of ``buses`` (empty on the copper plate)."""

    connected: tuple[bool, ...]
    buses: tuple[str, ...] = ()
    import_room_mw: tuple[float, ...] = ()
    export_room_mw: tuple[float, ...] = ()

    @property
    def islanded(self) -> bool:
        """Whether the grid islanded the hour in any of its sub-periods."""
        return not all(self.connected)

    def room(self, bus: str) -> tuple[float, float]:
        """(import room, export room) MW at ``bus``; KeyError on the copper plate or at a bus not on the feeder."""
        if bus not in self.buses:
            raise KeyError(f"no operating envelope at bus {bus!r}")
        i = self.buses.index(bus)
        return self.import_room_mw[i], self.export_room_mw[i]


@dataclass(frozen=True)
class SettlementDay:
    """What a rule settles, checked by ``settlement.settlement_day``: ``awards`` agent -> 24 P_sch (MW, + import),
    ``prices`` the 24 clearing prices ($/MWh) on a copper plate, the substation's (energy) prices on a feeder,
    ``agent_prices`` agent -> the 24 prices at its own bus (``price_of``: on a copper plate ``prices``), ``meter``
    agent -> {hour index 0..23: K readings of P_M (MW), None for a missing sub-period} (an absent hour is missing), ``subperiods`` K (dt = 1/K h), and each agent's
    registered ``max_import`` and ``max_export`` (MW): its readings lie in [-max_export, max_import]. ``grid`` is the
    24 hours' grid states as the DMO published them (hour index 0..23), None where they are not known (a recording
    cut before its last grid state, or a day settled by hand without them); ``bus`` agent -> its bus on a feeder
    (empty on the copper plate)."""

    awards: Mapping[str, tuple[float, ...]]
    prices: tuple[float, ...]
    meter: Meter
    subperiods: int
    max_import: Mapping[str, float]
    max_export: Mapping[str, float]
    agent_prices: Mapping[str, tuple[float, ...]] | None = None
    grid: tuple[GridHour, ...] | None = None
    bus: Mapping[str, str] = field(default_factory=dict)

    def price_of(self, agent: str) -> tuple[float, ...]:
        """The 24 prices the agent's energy is settled at: its bus's on a feeder, the clearing prices otherwise."""
        return self.prices if self.agent_prices is None else self.agent_prices[agent]

    @cached_property
    def exact_awards(self) -> dict[str, tuple[Fraction, ...]]:
        """Each agent's 24 P_sch exactly (``money.exact``), converted once for the rule and the statement alike."""
        return {agent: tuple(exact(p) for p in award) for agent, award in self.awards.items()}

    @cached_property
    def exact_prices(self) -> tuple[Fraction, ...]:
        """The 24 clearing prices exactly, converted once."""
        return tuple(exact(p) for p in self.prices)

    @cached_property
    def exact_agent_prices(self) -> dict[str, tuple[Fraction, ...]]:
        """Each agent's ``price_of`` exactly, converted once."""
        if self.agent_prices is None:
            return dict.fromkeys(self.awards, self.exact_prices)
        return {agent: tuple(exact(p) for p in self.agent_prices[agent]) for agent in self.awards}

    @property
    def dt(self) -> Fraction:
        """The length of a sub-period, 1/K hours, exactly."""
        return Fraction(1, self.subperiods)

    def readings(self, agent: str, hour: int) -> list[float | None]:
        """The agent's K readings of hour index ``hour``, None for each missing sub-period."""
        got = self.meter.get(agent, {}).get(hour)
        return [None] * self.subperiods if got is None else list(got)


@dataclass(frozen=True)
class Charges:
    """What a rule charges one agent for one hour, in $ (int, float, Fraction or Decimal; each rounded once,
    half-even, to the cent): the energy charge, the penalty and the credit (both >= 0) and, if given, their
    total, which must be energy_charge + penalty - credit to the cent."""

    energy_charge: object
    penalty: object
    credit: object = 0
    total: object = None


Rule = Callable[..., Mapping[str, Sequence[Charges]]]


@dataclass(frozen=True)
class DeviationPrice:
    """Money per hour ($/h) as a function of the deviation d = P_M - P_sch (MW): 0 at d = 0, then slope
    ``slopes[j]`` ($/MWh) between ``breakpoints[j-1]`` and ``breakpoints[j]`` (MW, increasing), so ``slopes`` has
    one more entry than ``breakpoints``. A negative value is money paid to the agent (a credit)."""

    breakpoints: tuple[Fraction, ...]
    slopes: tuple[Fraction, ...]

    def at(self, d: Fraction) -> Fraction:
        """f(d), exactly: the integral of the slope from 0 to d."""
        edges = (-math.inf, *self.breakpoints, math.inf)
        total = Fraction(0)
        for slope, lo, hi in zip(self.slopes, edges, edges[1:]):
            a, b = max(min(0, d), lo), min(max(0, d), hi)  # the part of [min(0,d), max(0,d)] in this segment
            if a < b:
                total += slope * (b - a) * (1 if d > 0 else -1)
        return total

    def worst(self, lo: Fraction, hi: Fraction) -> Fraction:
        """The largest f over [lo, hi]: a piecewise-linear function peaks at an end or a breakpoint."""
        return max(self.at(d) for d in (lo, hi, *(b for b in self.breakpoints if lo < b < hi)))

    @property
    def convex(self) -> bool:
        return all(a <= b for a, b in zip(self.slopes, self.slopes[1:]))

    def pieces(self) -> list[tuple[float, float]]:
        """Each segment's line, (slope $/MWh, intercept $/h): a convex f is their maximum, as the agent's model
        carries it (microgrid_agent/model/params.py, ``DeviationCost``)."""
        anchors = (self.breakpoints[0], *self.breakpoints) if self.breakpoints else (Fraction(0),)
        return [(float(slope), float(self.at(x) - slope * x)) for slope, x in zip(self.slopes, anchors)]


@dataclass(frozen=True)
class DeviationRule:
    """A built-in rule: each hour's deviation price from the rule's parameters, the hour's award and its clearing
    price, ``pricing(params, award_mw, price)``; ``defaults`` names every parameter and its default, ``ranges``
    the closed interval each may take."""

    name: str
    defaults: Mapping[str, float]
    pricing: Callable[[Mapping[str, Fraction], Fraction, Fraction], DeviationPrice]
    formula: str
    ranges: Mapping[str, tuple[float, float]]

    def __call__(self, day: SettlementDay, **params) -> dict[str, list[Charges]]:
        return {agent: [self._hour(day, agent, h, f)
                        for h, f in enumerate(self._hours(params, day.exact_awards[agent],
                                                          day.exact_agent_prices[agent]))]
                for agent in day.awards}

    def parameters(self, given: Mapping[str, object]) -> dict[str, float]:
        """The defaults overridden by ``given``; an unknown name or a value that is not a number in its range raises
        ValueError."""
        unknown = sorted(set(given) - set(self.defaults))
        if unknown:
            raise ValueError(f"{self.name} has no parameter {unknown[0]!r}; it takes {', '.join(self.defaults)}")
        out = dict(self.defaults)
        for key, value in given.items():
            low, high = self.ranges[key]
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not low <= value <= high:
                raise ValueError(f"{self.name}: {key} must be a number in {low:,g}..{high:,.15g}, got {value!r}")
            out[key] = float(value)
        return out

    def always_convex(self, params: Mapping[str, float]) -> bool:
        """Whether every hour's deviation price is convex at these parameters, whatever the award and the clearing
        price, so that an award carries it exactly (``deviation_cost``). No built-in's convexity depends on the
        award, and the only slope that moves with the price, price-linked's rate above the award, is least at a
        price of 0 (or below), where it is its floor: price 0 decides."""
        rates = {k: exact(v) for k, v in self.parameters(params).items()}
        return self.pricing(rates, Fraction(0), Fraction(0)).convex

    def hourly(self, params: Mapping[str, float], award: Sequence[float],
               prices: Sequence[float]) -> list[DeviationPrice]:
        """The 24 hourly deviation prices of an agent with this award (MW) at these clearing prices."""
        return self._hours(params, [exact(p) for p in award], [exact(p) for p in prices])

    def _hours(self, params: Mapping[str, float], award: Sequence[Fraction],
               prices: Sequence[Fraction]) -> list[DeviationPrice]:
        """``hourly`` of an award and prices already exact."""
        rates = {k: exact(v) for k, v in self.parameters(params).items()}
        return [self.pricing(rates, award[h], prices[h]) for h in range(HOURS)]

    def deviation_cost(self, params: Mapping[str, float], award: Sequence[float],
                       prices: Sequence[float]) -> list[list[tuple[float, float]]] | None:
        """One agent's 24 hourly deviation prices as pieces for its model, or None if one is not convex."""
        hours = self.hourly(params, award, prices)
        return [f.pieces() for f in hours] if all(f.convex for f in hours) else None

    def _hour(self, day: SettlementDay, agent: str, h: int, f: DeviationPrice) -> Charges:
        """One agent-hour under the hour's deviation price ``f``."""
        p_sch, price, dt = day.exact_awards[agent][h], day.exact_agent_prices[agent][h], day.dt
        readings = day.readings(agent, h)
        money = [f.at(exact(p) - p_sch) * dt for p in readings if p is not None]
        # A missing sub-period costs the worst the agent could have done within its registered limits, and earns
        # no credit: withholding data is never cheaper than reporting it (docs/settlement.md).
        worst = max(f.worst(-exact(day.max_export[agent]) - p_sch, exact(day.max_import[agent]) - p_sch), 0) * dt
        penalty = sum((m for m in money if m > 0), Fraction(0)) + worst * readings.count(None)
        credit = sum((-m for m in money if m < 0), Fraction(0))
        return Charges(energy_charge=price * p_sch, penalty=penalty, credit=credit)


def _paper(r, award, price) -> DeviationPrice:
    return DeviationPrice((Fraction(0),), (r["credit"], r["penalty"]))


def _symmetric(r, award, price) -> DeviationPrice:
    return DeviationPrice((Fraction(0),), (-r["below"], r["above"]))


def _deadband(r, award, price) -> DeviationPrice:
    band = max(r["band_mw"], r["band_share"] * abs(award))
    return DeviationPrice((-band, band), (-r["below_rate"], Fraction(0), r["rate"]))


def _price_linked(r, award, price) -> DeviationPrice:
    return DeviationPrice((Fraction(0),), (r["credit"], max(r["k"] * price, r["floor"])))


_RATE, _MW, _SHARE, _FACTOR = (0.0, MAX_RATE), (0.0, MAX_MW), (0.0, 1.0), (0.0, MAX_PRICE_FACTOR)
BUILT_IN: dict[str, DeviationRule] = {rule.name: rule for rule in (
    DeviationRule("paper", {"penalty": 150.0, "credit": 0.0}, _paper,
                  "penalty x max(d, 0) - credit x max(-d, 0)", {"penalty": _RATE, "credit": _RATE}),
    DeviationRule("symmetric", {"above": 150.0, "below": 75.0}, _symmetric,
                  "above x max(d, 0) + below x max(-d, 0)", {"above": _RATE, "below": _RATE}),
    DeviationRule("deadband", {"rate": 150.0, "below_rate": 0.0, "band_mw": 0.0, "band_share": 0.1}, _deadband,
                  "rate x max(d - b, 0) + below_rate x max(-d - b, 0), b = max(band_mw, band_share x |P_sch|)",
                  {"rate": _RATE, "below_rate": _RATE, "band_mw": _MW, "band_share": _SHARE}),
    DeviationRule("price-linked", {"k": 1.5, "floor": 50.0, "credit": 0.0}, _price_linked,
                  "max(k x price, floor) x max(d, 0) - credit x max(-d, 0)",
                  {"k": _FACTOR, "floor": _RATE, "credit": _RATE}),
)}


def market_parameters(rule: DeviationRule, given: Mapping[str, float], penalty: float | None, credit: float,
                      case_penalty: float) -> dict[str, float]:
    """The parameters a built-in rule named with ``given`` settles by beside the market's ``penalty`` ($/MWh above
    the award; None: not set, the case's ``case_penalty``) and ``credit`` ($/MWh below it; 0: not set), or
    ValueError, one line, where the two disagree (docs/settlement.md, "The rule and the market's penalty"):

    - ``paper`` takes each rate it is not given from the market; a rate given both ways must be the same;
    - another built-in prices every deviation by its own parameters, so a penalty or credit beside it would be
      ignored and is refused, unless the rule is not convex at its parameters: an award cannot carry it then, and
      the agents schedule against the market's penalty and credit instead.
    """
    params = dict(given)
    if rule.name == "paper":
        for key, market in (("penalty", penalty), ("credit", credit or None)):
            if market is not None and key in params and params[key] != market:
                raise ValueError(f"settlement rule paper:{key}={params[key]:g} and a market {key} of {market:g} "
                                 f"$/MWh disagree: give the {key} once")
        params.setdefault("penalty", case_penalty if penalty is None else penalty)
        params.setdefault("credit", credit)
        rule.parameters(params)  # each in its range
        return params
    if (penalty is not None or credit) and rule.always_convex(params):
        raise ValueError(f"settlement rule {rule.name} prices every deviation by its own parameters "
                         f"({', '.join(rule.defaults)}): a market penalty or credit beside it would be ignored; "
                         "leave them unset, or settle by the paper rule")
    return params
