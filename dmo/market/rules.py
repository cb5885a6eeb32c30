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
from dataclasses import dataclass
from fractions import Fraction

from scenarios.horizon import HOURS

from .money import exact

Meter = Mapping[str, Mapping[int, Sequence[float | None]]]


@dataclass(frozen=True)
class SettlementDay:
    """What a rule settles, checked by ``settlement.settlement_day``: ``awards`` agent -> 24 P_sch (MW, + import),
    ``prices`` the 24 clearing prices ($/MWh), ``meter`` agent -> {hour index 0..23: K readings of P_M (MW), None
    for a missing sub-period} (an absent hour is missing), ``subperiods`` K (dt = 1/K h), and each agent's
    registered ``max_import`` and ``max_export`` (MW): its readings lie in [-max_export, max_import]."""

    awards: Mapping[str, tuple[float, ...]]
    prices: tuple[float, ...]
    meter: Meter
    subperiods: int
    max_import: Mapping[str, float]
    max_export: Mapping[str, float]

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
    price, ``pricing(params, award_mw, price)``; ``defaults`` names every parameter and its default."""

    name: str
    defaults: Mapping[str, float]
    pricing: Callable[[Mapping[str, Fraction], Fraction, Fraction], DeviationPrice]
    formula: str

    def __call__(self, day: SettlementDay, **params) -> dict[str, list[Charges]]:
        return {agent: [self._hour(day, agent, h, f) for h, f in enumerate(self.hourly(params, award, day.prices))]
                for agent, award in day.awards.items()}

    def parameters(self, given: Mapping[str, object]) -> dict[str, float]:
        """The defaults overridden by ``given``; an unknown name or a value that is not a finite number >= 0 raises
        ValueError."""
        unknown = sorted(set(given) - set(self.defaults))
        if unknown:
            raise ValueError(f"{self.name} has no parameter {unknown[0]!r}; it takes {', '.join(self.defaults)}")
        out = dict(self.defaults)
        for key, value in given.items():
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value) or value < 0:
                raise ValueError(f"{self.name}: {key} must be a finite number >= 0, got {value!r}")
            out[key] = float(value)
        return out

    def hourly(self, params: Mapping[str, float], award: Sequence[float],
               prices: Sequence[float]) -> list[DeviationPrice]:
        """The 24 hourly deviation prices of an agent with this award (MW) at these clearing prices."""
        rates = {k: exact(v) for k, v in self.parameters(params).items()}
        return [self.pricing(rates, exact(award[h]), exact(prices[h])) for h in range(HOURS)]

    def deviation_cost(self, params: Mapping[str, float], award: Sequence[float],
                       prices: Sequence[float]) -> list[list[tuple[float, float]]] | None:
        """One agent's 24 hourly deviation prices as pieces for its model, or None if one is not convex."""
        hours = self.hourly(params, award, prices)
        return [f.pieces() for f in hours] if all(f.convex for f in hours) else None

    def _hour(self, day: SettlementDay, agent: str, h: int, f: DeviationPrice) -> Charges:
        """One agent-hour under the hour's deviation price ``f``."""
        p_sch, price = exact(day.awards[agent][h]), exact(day.prices[h])
        dt = Fraction(1, day.subperiods)
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


BUILT_IN: dict[str, DeviationRule] = {rule.name: rule for rule in (
    DeviationRule("paper", {"penalty": 150.0, "credit": 0.0}, _paper,
                  "penalty x max(d, 0) - credit x max(-d, 0)"),
    DeviationRule("symmetric", {"above": 150.0, "below": 75.0}, _symmetric,
                  "above x max(d, 0) + below x max(-d, 0)"),
    DeviationRule("deadband", {"rate": 150.0, "below_rate": 0.0, "band_mw": 0.0, "band_share": 0.1}, _deadband,
                  "rate x max(d - b, 0) + below_rate x max(-d - b, 0), b = max(band_mw, band_share x |P_sch|)"),
    DeviationRule("price-linked", {"k": 1.5, "floor": 50.0, "credit": 0.0}, _price_linked,
                  "max(k x price, floor) x max(d, 0) - credit x max(-d, 0)"),
)}
