"""Price-responsive hourly step bids from the agent's own schedule at several price levels (docs/agent.md): the
maths of the default bidding strategy, ``price-response`` (strategies.py).

The agent asks itself "how much would I import in each hour if grid energy cost m x the ISO price?" for a few
multipliers m, and turns the answers into the hourly price-quantity steps of its bid (``messages.BidStep``). Each
answer is the deterministic expected-value model: one scenario holding the exact mean of the sampled forecast
errors, always grid-connected, the award not binding (P^sch = P_M^max, no penalty) and P_M bought or sold at the
price. The expected-value model, not the stochastic one, because a bid needs one quantity per price and hour, and six
extensive-form MILPs would not fit a bidding deadline; its error is the value of the stochastic solution, which
the day-ahead schedule (solved against the award) recovers.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from messages import BidStep
from messages.schemas import MAX_BID_STEPS
from scenarios.case import Case
from scenarios.generation import ScenarioSet, expected_value, forecast_scenario, sample
from scenarios.horizon import HOURS, hourly

from ..model import Model, Params, build
from ..schedule import StochasticSchedule
from ..solvers.extensive import solve_model

DEFAULT_MULTIPLIERS = (0.5, 0.8, 1.0, 1.25, 1.6, 2.5)
QUANTUM = 1e-6  # MW: quantities are rounded to this, so solver noise never makes a step of its own


@dataclass(frozen=True)
class PriceResponse:
    """The agent's import at each price level: ``prices`` (M, 24) = m x ISO price, ``raw`` (M, 24) the hourly
    mean P_M of each solve (MW, + import), ``quantity`` (M, 24) the same made non-increasing in price per hour.
    ``schedules`` and ``params`` are the M solves, ``scenario`` what they were solved on (for the checker)."""

    multipliers: tuple[float, ...]
    prices: np.ndarray
    raw: np.ndarray
    quantity: np.ndarray
    scenario: ScenarioSet
    schedules: tuple[StochasticSchedule, ...]
    params: tuple[Params, ...]


def _check_multipliers(multipliers: Sequence[float]) -> tuple[float, ...]:
    out = tuple(sorted({float(m) for m in multipliers}))
    if not out:
        raise ValueError("at least one price multiplier is needed")
    if len(out) > MAX_BID_STEPS:
        raise ValueError(f"at most {MAX_BID_STEPS} price multipliers (steps per hour), got {len(out)}")
    if not all(math.isfinite(m) and m > 0 for m in out):
        raise ValueError(f"price multipliers must be finite and > 0, got {out}")
    return out


def monotone(prices: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """Per hour, the largest curve below ``raw`` that is non-increasing in price (a running minimum in price order).

    Each solve is a MIP solved to a gap and the hours are coupled, so the raw answers can rise with the price by
    solver noise or a different commitment; a bid must not. Solves at one price (an ISO price of 0) share their
    least quantity, so every price has one quantity.
    """
    out = np.empty_like(raw)
    for t in range(raw.shape[1]):
        order = np.argsort(prices[:, t], kind="stable")
        p, q = prices[order, t], raw[order, t]
        for value in np.unique(p):
            q[p == value] = q[p == value].min()
        out[order, t] = np.minimum.accumulate(q)
    return out


def price_response(case: Case, iso_price: Sequence[float], subperiods: int = 1,
                   multipliers: Sequence[float] = DEFAULT_MULTIPLIERS, seed: int = 0, gap: float = 1e-4,
                   sample_size: int = 0, time_limit: float | None = None) -> PriceResponse:
    """Solve the expected-value model once per multiplier with grid energy at m x ``iso_price`` ($/MWh, 24).

    ``sample_size`` 0 uses the exact expected forecast (``forecast_scenario``); n > 0 the mean of n sampled
    grid-connected scenarios of ``seed`` instead.
    """
    iso = np.asarray(hourly(iso_price, "iso_price"))
    ms = _check_multipliers(multipliers)
    if sample_size > 0:
        scen = expected_value(sample(case, sample_size, subperiods, island_hours=0, seed=seed))
    else:
        scen = forecast_scenario(case, subperiods)
    award = np.full(HOURS, case.grid.p_m_max)
    params, schedules, raw = [], [], []
    started = time.perf_counter()  # the first model's timings include building it
    for model in priced(case, scen, award, iso, ms):
        schedule = solve_model(model, started, gap=gap, time_limit=time_limit)
        started = time.perf_counter()
        params.append(model.params)
        schedules.append(schedule)
        raw.append(schedule.dispatch.p_m[0].reshape(HOURS, subperiods).mean(axis=1))
    prices = np.outer(ms, iso)
    raw = np.round(np.array(raw) / QUANTUM) * QUANTUM
    return PriceResponse(ms, prices, raw, monotone(prices, raw), scen, tuple(schedules), tuple(params))


def priced(case: Case, scen: ScenarioSet, award: np.ndarray, iso: np.ndarray,
           multipliers: tuple[float, ...]) -> Iterator[Model]:
    """The expected-value model at each multiplier m, built once: its grid energy term is scaled by a Parameter
    set to m, so cvxpy compiles the model for the first price and only re-applies the Parameter for the others
    (a bid's six models compiled one by one took about 60% of its time)."""
    base = build(case, scen, Params(p_sch=award, penalty=0.0, import_price=iso))
    scale = cp.Parameter(nonneg=True)
    terms = {**base.terms, "energy": scale * base.terms["energy"]}
    problem = cp.Problem(cp.Minimize(sum(terms.values())), base.problem.constraints)
    for m in multipliers:
        scale.value = m
        params = Params(p_sch=award, penalty=0.0, import_price=m * iso)
        yield dataclasses.replace(base, problem=problem, params=params, terms=terms)


def hour_steps(prices: np.ndarray, quantity: np.ndarray) -> tuple[BidStep, ...]:
    """Steps whose net accepted quantity at price ``prices[k]`` is ``quantity[k]`` (non-increasing in price).

    With prices ascending, a purchase of q_k+ - q_(k+1)+ at lambda_k is accepted at every clearing price <=
    lambda_k and a sale of -(q_k- - q_(k-1)-) at lambda_k at every price >= lambda_k, so at lambda_j the purchases
    add up to q_j+ and the sales to -q_j-: net q_j. Between two prices the curve steps; below the lowest it
    buys q_1+, above the highest it sells q_M-. Zero steps are dropped.
    """
    p, first = np.unique(np.asarray(prices, float), return_index=True)
    q = np.asarray(quantity, float)[first]
    if np.any(np.diff(q) > QUANTUM / 2):
        raise ValueError("quantity must be non-increasing in price")
    buy, sell = np.maximum(q, 0.0), np.maximum(-q, 0.0)
    purchases = buy - np.append(buy[1:], 0.0)
    sales = -(sell - np.insert(sell[:-1], 0, 0.0))
    steps = []
    for price, b, s in zip(p, purchases, sales):
        for amount in (b, s):
            amount = round(amount / QUANTUM) * QUANTUM
            if amount != 0.0:
                steps.append(BidStep(price_per_mwh=float(price), quantity_mw=float(amount)))
    return tuple(steps)


def curve_of(response: PriceResponse) -> tuple[tuple[BidStep, ...], ...]:
    """The 24 hours of steps of a price response."""
    return tuple(hour_steps(response.prices[:, t], response.quantity[:, t]) for t in range(HOURS))


def bid_curve(case: Case, iso_price: Sequence[float], subperiods: int = 1,
              multipliers: Sequence[float] = DEFAULT_MULTIPLIERS, seed: int = 0, gap: float = 1e-4,
              sample_size: int = 0, time_limit: float | None = None) -> tuple[tuple[BidStep, ...], ...]:
    """The agent's hourly step bids (24 tuples of ``messages.BidStep``, at most 16 steps each) for the ISO price
    of the DMO's call for bids; see ``price_response`` for the options."""
    return curve_of(price_response(case, iso_price, subperiods, multipliers, seed, gap, sample_size, time_limit))
