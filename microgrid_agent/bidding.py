"""Price-responsive hourly step bids from the agent's own schedule at several price levels (docs/agent.md).

The agent asks itself "how much would I import in each hour if grid energy cost m x the ISO price?" for a few
multipliers m, and turns the answers into the step bids of SPEC section 6 (``dmo.clearing.Step``). Each answer is
the deterministic expected-value model: one scenario holding the exact mean of the sampled forecast errors, always
grid-connected, the award not binding (P^sch = P_M^max, no penalty) and P_M bought or sold at the price. The
expected-value model, not the stochastic one, because a bid needs one quantity per price and hour, and six
extensive-form MILPs would not fit a bidding deadline; its error is the value of the stochastic solution, which
the day-ahead schedule (solved against the award) recovers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dmo.clearing import Step, hourly
from scenarios.case import HOURS, Case
from scenarios.generation import ScenarioSet, expected_value, sample

from .model import Params
from .schedule import Schedule
from .solve import solve

DEFAULT_MULTIPLIERS = (0.5, 0.8, 1.0, 1.25, 1.6, 2.5)
MAX_STEPS = 16  # messages.schemas.MAX_BID_STEPS: the wire's limit per hour
QUANTUM = 1e-6  # MW: quantities are rounded to this, so solver noise never makes a step of its own


def _clipped_mean(forecast: np.ndarray, bound: float, capacity: float) -> np.ndarray:
    """E[min(f (1 + b e), cap)] for e ~ U(-1, 1): the mean availability ``sample`` draws (clipped at capacity).

    Where f (1 + b) <= cap nothing is clipped and the mean is f. Otherwise, with e* = (cap / f - 1) / b the error
    at which the clip starts, the mean is (1/2) [f ((e* + 1) + b (e*^2 - 1) / 2) + cap (1 - e*)].
    """
    f = np.asarray(forecast, float)
    clipped = (bound > 0) & (f * (1.0 + bound) > capacity)
    safe_f = np.where(clipped, f, 1.0)
    e = np.where(clipped, (capacity / safe_f - 1.0) / max(bound, 1e-300), 1.0)
    mean = 0.5 * (safe_f * ((e + 1.0) + bound * (e * e - 1.0) / 2.0) + capacity * (1.0 - e))
    return np.where(clipped, mean, f)


def forecast_scenario(case: Case, subperiods: int) -> ScenarioSet:
    """One grid-connected scenario of probability 1 holding the exact expected load and renewable availability
    of ``scenarios.generation.sample`` (the forecast; renewables slightly below it where the error is clipped)."""
    if subperiods < 1:
        raise ValueError(f"subperiods must be at least 1 per hour, got {subperiods}")
    load = np.repeat(np.asarray(case.fixed_load.forecast, float), subperiods)[None, :]
    renewable = np.zeros((len(case.renewables), 1, HOURS * subperiods))
    for r, unit in enumerate(case.renewables):
        mean = _clipped_mean(np.asarray(unit.forecast), case.uncertainty.for_renewable(unit.name), unit.capacity)
        renewable[r, 0] = np.repeat(mean, subperiods)
    return ScenarioSet(subperiods, np.ones(1), load, renewable, np.ones((1, HOURS * subperiods)))


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
    schedules: tuple[Schedule, ...]
    params: tuple[Params, ...]


def _check_multipliers(multipliers: Sequence[float]) -> tuple[float, ...]:
    out = tuple(sorted({float(m) for m in multipliers}))
    if not out:
        raise ValueError("at least one price multiplier is needed")
    if len(out) > MAX_STEPS:
        raise ValueError(f"at most {MAX_STEPS} price multipliers (steps per hour), got {len(out)}")
    if not all(math.isfinite(m) and m > 0 for m in out):
        raise ValueError(f"price multipliers must be finite and > 0, got {out}")
    return out


def _monotone(prices: np.ndarray, raw: np.ndarray) -> np.ndarray:
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
    for m in ms:
        p = Params(p_sch=award, penalty=0.0, import_price=m * iso)
        schedule = solve(case, scen, p, gap=gap, time_limit=time_limit)
        params.append(p)
        schedules.append(schedule)
        raw.append(schedule.dispatch.p_m[0].reshape(HOURS, subperiods).mean(axis=1))
    prices = np.outer(ms, iso)
    raw = np.round(np.array(raw) / QUANTUM) * QUANTUM
    return PriceResponse(ms, prices, raw, _monotone(prices, raw), scen, tuple(schedules), tuple(params))


def hour_steps(prices: np.ndarray, quantity: np.ndarray) -> tuple[Step, ...]:
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
                steps.append(Step(float(price), float(amount)))
    return tuple(steps)


def curve_of(response: PriceResponse) -> tuple[tuple[Step, ...], ...]:
    """The 24 hours of steps of a price response."""
    return tuple(hour_steps(response.prices[:, t], response.quantity[:, t]) for t in range(HOURS))


def bid_curve(case: Case, iso_price: Sequence[float], subperiods: int = 1,
              multipliers: Sequence[float] = DEFAULT_MULTIPLIERS, seed: int = 0, gap: float = 1e-4,
              sample_size: int = 0, time_limit: float | None = None) -> tuple[tuple[Step, ...], ...]:
    """The agent's hourly step bids (24 tuples of ``dmo.clearing.Step``, at most 16 steps each) for the ISO price
    of the DMO's call for bids; see ``price_response`` for the options."""
    return curve_of(price_response(case, iso_price, subperiods, multipliers, seed, gap, sample_size, time_limit))
