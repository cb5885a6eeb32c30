"""Bidding strategies: the object that turns the DMO's call for bids into an agent's 24 hours of bid steps, chosen
per agent, built in or a user's own (docs/strategies.md).

A strategy has one method, ``bids(call, microgrid)``, and may have a second, ``observe(result)``, which the agent
calls at the end of each day with what it learned (``DayLearned``); an object keeps whatever state it likes between
days. ``NAME[:key=value,...]`` names a built-in (``price-response``, ``table1``, ``naive``);
``path/to/strategy.py:Class[:key=value,...]`` or ``module:Class[:key=value,...]`` a class of one's own, made with
the parameters as keyword arguments. ``strategy_name`` checks a name without importing anything; ``choose_strategy``
makes the strategy and tries it on a trial call before it bids for real; ``ChosenStrategy.bid`` checks every bid a
strategy returns before it goes on the wire.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from messages import DMO, Award, BidStep, CallForBids, DaySummary, SettlementStatement
from messages.schemas import MAX_BID_STEPS, PRICE_CAP, PRICE_FLOOR
from scenarios.case import Case
from scenarios.fleet import MAX_SCALE
from scenarios.horizon import HOURS

from ..usercode import CodeKind, check_target, code_of, load, params_text, split_spec

STRATEGY = CodeKind("strategy", "class", "path/to/strategy.py", "dmosim_strategy_")
DEFAULT_STRATEGY = "price-response"
Curve = tuple[tuple[BidStep, ...], ...]
NO_BID: Curve = ((),) * HOURS  # no offer in any hour: what an agent whose strategy failed sends


@dataclass(frozen=True)
class Microgrid:
    """What a strategy is told of its agent when it bids: the agent's id, the day's ``case`` (the state the day
    before ended in, profiles scaled as the run says), which ``day`` of the run (1 first) and ``market_day``,
    ``seed`` the day's own seed of the agent's scenarios (``scenarios.days.day_seed``), and ``gap`` the relative MIP
    gap of the agent's solves."""

    agent: str
    case: Case
    day: int
    market_day: str
    seed: int
    gap: float


@dataclass(frozen=True)
class DayLearned:
    """What the agent learned of a day, given to ``observe`` at its end: the ``bid`` it sent, its ``award`` (clearing
    prices and P_sch), its ``statement`` and the DMO's day ``summary``; each None if it never came."""

    day: int
    market_day: str
    bid: Curve
    award: Award | None
    statement: SettlementStatement | None
    summary: DaySummary | None

    @property
    def clearing_prices(self) -> tuple[float, ...] | None:
        """The day's 24 clearing prices, $/MWh, from the award or else the summary; None if neither came."""
        for msg in (self.award, self.summary):
            if msg is not None:
                return tuple(msg.clearing_price_per_mwh)
        return None


class Strategy(Protocol):
    """A bidding strategy. ``bids`` returns 24 sequences of ``messages.BidStep``, hour 1 first, at most 16 steps
    each (an empty one offers nothing that hour). A strategy may also define ``observe(result: DayLearned) -> None``,
    called once at the end of each day; it is optional, so it is not part of this protocol's check."""

    def bids(self, call: CallForBids, microgrid: Microgrid) -> Curve: ...


class RespondToPrice:
    """The agent's price response (``microgrid_agent.agent.bidding.bid_curve``, docs/agent.md): at each multiplier m
    of the ISO price, the import the expected-value model of the paper's objective (1) under constraints (2)-(18)
    chooses with grid energy at m x the price, made non-increasing in price per hour and cut into steps. The
    default, and what every agent bid before strategies could be chosen."""

    def bids(self, call: CallForBids, microgrid: Microgrid) -> Curve:
        from .bidding import bid_curve  # noqa: PLC0415  (the solver stack: naming a strategy must not load it)

        return bid_curve(microgrid.case, np.asarray(call.iso_price_per_mwh), seed=microgrid.seed, gap=microgrid.gap)


class TableOne:
    """The case's own award (its ``grid.p_sch``: for the paper's case the scheduled transfer of Table I of Parhizi
    & Khodaei), times ``scale`` as in the paper's Fig. 3, bid at any price: each hour an import q > 0 is bought at the
    call's price cap and an export q < 0 sold at its price floor, so the market awards it whenever the feeder allows.
    The paper's market outcome taken as a bid: a strategy that ignores prices."""

    def __init__(self, scale: float = 1.0):
        if not 0 <= scale <= MAX_SCALE:
            raise ValueError(f"strategy table1: scale must be in [0, {MAX_SCALE:g}], got {scale:g}")
        self.scale = scale

    def bids(self, call: CallForBids, microgrid: Microgrid) -> Curve:
        q = self.scale * np.asarray(microgrid.case.grid.p_sch, float)
        return tuple(_one_step(float(q[t]), call.price_cap_per_mwh if q[t] > 0 else call.price_floor_per_mwh)
                     for t in range(HOURS))


class Naive:
    """The forecast net load bid at the ISO price: each hour, fixed load plus each adjustable load's energy E_d spread
    evenly over its window [alpha, beta] (16), less the renewable forecasts, within +-P_M^max (18); bought (or, when
    negative, sold) at that hour's ISO price. A microgrid that runs no unit and no storage against the market: the
    baseline the paper's scheduling is measured against."""

    def bids(self, call: CallForBids, microgrid: Microgrid) -> Curve:
        net = net_load(microgrid.case)
        return tuple(_one_step(float(net[t]), float(call.iso_price_per_mwh[t])) for t in range(HOURS))


def net_load(case: Case) -> np.ndarray:
    """The forecast net load of ``case``, MW per hour (``Naive``): what it would import with no unit and no storage."""
    load = np.asarray(case.fixed_load.forecast, float).copy()
    for d in case.loads:
        load[d.alpha - 1:d.beta] += d.energy / (d.beta - d.alpha + 1)
    for r in case.renewables:
        load -= np.asarray(r.forecast, float)
    return np.clip(load, -case.grid.p_m_max, case.grid.p_m_max)


def _one_step(quantity: float, price: float) -> tuple[BidStep, ...]:
    return (BidStep(price_per_mwh=float(price), quantity_mw=quantity),) if quantity != 0 else ()


STRATEGIES: dict[str, type] = {DEFAULT_STRATEGY: RespondToPrice, "table1": TableOne, "naive": Naive}


class StrategyError(ValueError):
    """A strategy that cannot be used, or failed when it bid or observed: one line naming it and the problem."""


@dataclass(frozen=True)
class StrategyName:
    """A strategy as named, checked without loading anything: ``target`` a built-in's name or ``where:Class``,
    ``params`` the parameters given."""

    target: str
    params: Mapping[str, float] = field(default_factory=dict)

    @property
    def built_in(self) -> bool:
        return self.target in STRATEGIES

    @property
    def code(self) -> str | None:
        """The code a strategy of one's own would run (``microgrid_agent.usercode.code_of``); None for a built-in."""
        return None if self.built_in else code_of(self.target)

    @property
    def label(self) -> str:
        """The strategy as one would name it again, parameters included: ``table1:scale=0.5``."""
        params = params_text(self.params)
        return f"{self.target}:{params}" if params else self.target


def strategy_name(spec: str) -> StrategyName:
    """``spec`` checked as a name, importing and running no code of a user's: its syntax, and a built-in's parameters.
    StrategyError, one line, when it names no strategy. All that reading a file that names a strategy (an
    experiment, a fleet, a recording) does with it; only ``choose_strategy`` loads one."""
    try:
        target, params = split_spec(spec, STRATEGY)
        if target in STRATEGIES:
            _check_params(target, STRATEGIES[target], params)
            STRATEGIES[target](**params)  # a built-in's own check of its values: ours, so it may run here
        elif ":" in target:
            check_target(target, STRATEGY)
        else:
            raise ValueError(f"unknown strategy {target!r}: the built-in strategies are {', '.join(STRATEGIES)}; a "
                             "strategy of your own is path/to/strategy.py:Class or module:Class")
    except ValueError as err:
        raise StrategyError(str(err)) from None
    return StrategyName(target, params)


def _check_params(target: str, cls: type, params: Mapping[str, float]) -> None:
    """The parameters name keyword arguments of ``cls`` (one taking ``**kwargs`` takes any)."""
    accepted = inspect.signature(cls).parameters
    if any(p.kind is p.VAR_KEYWORD for p in accepted.values()):
        return
    for key in params:
        if key not in accepted:
            names = ", ".join(accepted) or "none"
            raise ValueError(f"strategy {target} has no parameter {key!r} (its parameters: {names})")


@dataclass(frozen=True)
class ChosenStrategy:
    """A strategy made from its name: ``name`` (``StrategyName``) and the object that bids."""

    name: StrategyName
    strategy: Strategy = field(compare=False)

    @property
    def label(self) -> str:
        return self.name.label

    def bid(self, call: CallForBids, microgrid: Microgrid) -> Curve:
        """The strategy's bid for ``call``, checked (``checked_curve``); StrategyError, one line, if it raises or
        returns what is not a bid."""
        try:
            curve = self.strategy.bids(call, microgrid)
        except Exception as err:  # a user's code may fail in any way: say how, in one line
            raise StrategyError(f"strategy {self.label} failed: {type(err).__name__}: {_line(err)}") from None
        try:
            return checked_curve(curve)
        except Exception as err:  # what a user's code returns may fail even to be looked at (a __len__ that raises)
            raise StrategyError(f"strategy {self.label} returned no bid: {_line(err)}") from None

    def observe(self, result: DayLearned) -> None:
        """Tell the strategy how the day went, if it listens (``observe``); StrategyError, one line, if it raises."""
        observe = getattr(self.strategy, "observe", None)
        if observe is None:
            return
        try:
            observe(result)
        except Exception as err:  # a user's code may fail in any way: say how, in one line
            raise StrategyError(f"strategy {self.label} failed to observe day {result.day}: "
                                f"{type(err).__name__}: {_line(err)}") from None


def _line(err: Exception) -> str:
    return " ".join(str(err).split())[:300]


def checked_curve(curve) -> Curve:
    """``curve`` as the bid's 24 hours of steps, or ValueError, one line: it must be 24 sequences, hour 1 first,
    of at most ``MAX_BID_STEPS`` ``messages.BidStep`` each, with finite prices and quantities (the bid's schema,
    docs/protocol.md)."""
    if isinstance(curve, (str, bytes, Mapping)) or not hasattr(curve, "__len__"):
        raise ValueError(f"expected {HOURS} hours of steps, got {type(curve).__name__}")
    if len(curve) != HOURS:
        raise ValueError(f"{len(curve)} hours of steps, not {HOURS}")
    hours = []
    for t, steps in enumerate(curve, start=1):
        if isinstance(steps, (str, bytes, Mapping)) or not hasattr(steps, "__len__"):
            raise ValueError(f"hour {t}: expected a sequence of BidStep, got {type(steps).__name__}")
        if len(steps) > MAX_BID_STEPS:
            raise ValueError(f"hour {t}: {len(steps)} steps, at most {MAX_BID_STEPS}")
        for k, step in enumerate(steps, start=1):
            if type(step) is not BidStep:
                raise ValueError(f"hour {t}, step {k}: {type(step).__name__}, not a messages.BidStep")
            if not all(_finite(v) for v in (step.price_per_mwh, step.quantity_mw)):  # a model_construct'ed step
                raise ValueError(f"hour {t}, step {k}: price and quantity must be finite numbers")
        hours.append(tuple(steps))
    return tuple(hours)


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def strategy_class(name: StrategyName) -> type:
    """The class ``name`` names: a built-in's, or one of one's own, its module imported (so its code runs) here;
    StrategyError, one line, if it cannot be loaded or does not take the parameters."""
    if name.built_in:
        return STRATEGIES[name.target]
    try:
        cls = load(name.target, STRATEGY)
        _check_params(name.target, cls, name.params)
    except ValueError as err:
        raise StrategyError(str(err)) from None
    return cls


def make_strategy(name: StrategyName, cls: type | None = None) -> ChosenStrategy:
    """A fresh object of the strategy ``name`` names (of ``cls``, its class, if already loaded), its parameters as
    keyword arguments; StrategyError, one line, if it cannot be made or has no ``bids`` method."""
    cls = cls or strategy_class(name)
    try:
        strategy = cls(**name.params)
    except Exception as err:  # a user's class may refuse its parameters in any way
        raise StrategyError(f"strategy {name.label}: cannot be made: {type(err).__name__}: {_line(err)}") from None
    if not callable(getattr(strategy, "bids", None)):
        raise StrategyError(f"strategy {name.label}: {type(strategy).__name__} has no method bids(call, microgrid)")
    return ChosenStrategy(name, strategy)


def trial_call(case: Case) -> CallForBids:
    """A call for bids such as a DMO sends, at ``case``'s ISO price: what a strategy is tried on before it bids."""
    return CallForBids(sender=DMO, market_day="2000-01-01", iso_price_per_mwh=tuple(case.grid.iso_price),
                       price_floor_per_mwh=PRICE_FLOOR, price_cap_per_mwh=PRICE_CAP, import_limit_mw=case.grid.p_m_max,
                       export_limit_mw=case.grid.p_m_max, penalty_per_mwh=case.grid.penalty, subperiods=1,
                       deadline_s=600.0)


def choose_strategy(spec: str, case: Case, gap: float = 0.01) -> ChosenStrategy:
    """The strategy ``spec`` names, made and, if it is a user's own, tried once on a trial call for ``case``
    (``trial_call``; a throwaway object, so the one that bids starts with no memory of it); StrategyError, one line,
    if it cannot be used. Only for a strategy the user named, or one a file names that ``Trust`` allows."""
    name = strategy_name(spec)
    cls = strategy_class(name)
    if not name.built_in:
        trial = make_strategy(name, cls)
        trial.bid(trial_call(case), Microgrid("trial", case, 1, "2000-01-01", 0, gap))
    return make_strategy(name, cls)
