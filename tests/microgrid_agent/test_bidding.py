"""Step bids from the expected-value model at several prices: the curve clears where the model says, and is monotone."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmo.market.clearing import clear
from dmo.operator.markets import bid_curve as received_bid
from messages import Bid, BidStep
from messages.schemas import MAX_BID_STEPS
from microgrid_agent.agent.bidding import (DEFAULT_MULTIPLIERS, bid_curve, curve_of, hour_steps, monotone,
                                           price_response)
from microgrid_agent.checker import check_schedule
from microgrid_agent.solvers.extensive import solve
from scenarios.case import load_case
from scenarios.generation import clipped_mean, forecast_scenario, sample

BIG = 1e6  # MW: feeder limits that never bind
TOL = 1e-6  # MW


@pytest.fixture(scope="module")
def case():
    return load_case("paper")


@pytest.fixture(scope="module")
def response(case):
    """The paper case's price response at hourly resolution, every solve verified by the checker."""
    resp = price_response(case, case.grid.iso_price, subperiods=1)
    for schedule, params in zip(resp.schedules, resp.params):
        check_schedule(case, resp.scenario, schedule, p_sch=params.p_sch, penalty=params.penalty,
                       import_price=params.import_price).raise_if_failed()
    return resp


def cleared(curve, price):
    """The award of a lone bidder at ISO price ``price`` (scalar or 24) with limits that never bind, its bid read as
    the DMO reads a received one."""
    bid = Bid(sender="mg1", market_day="2026-07-01", hours=curve)
    return np.array(clear([received_bid(bid)], price, BIG, BIG).awards["mg1"])


def test_award_at_iso_price_is_the_models_import(case, response):
    k = response.multipliers.index(1.0)
    curve = curve_of(response)
    np.testing.assert_allclose(cleared(curve, case.grid.iso_price), response.quantity[k], atol=TOL)
    # the running minimum only repairs what the solves got wrong: at the ISO price it matches the solve
    np.testing.assert_allclose(response.quantity[k], response.raw[k], atol=1e-3)


def test_award_at_every_price_level_is_its_quantity(case, response):
    curve = curve_of(response)
    for k in range(len(response.multipliers)):
        np.testing.assert_allclose(cleared(curve, response.prices[k]), response.quantity[k], atol=TOL)


def test_each_price_level_solved_on_one_compiled_model_costs_what_a_model_built_at_that_price_costs(case, response):
    """The six price levels share one model whose grid energy term a Parameter scales; each solve is the one a
    model built at its price gives, within the gap (1e-4); the fixture's checker priced each one's energy at its
    own price."""
    for schedule, params in zip(response.schedules, response.params):
        alone = solve(case, response.scenario, params, gap=1e-4)
        assert schedule.objective == pytest.approx(alone.objective, rel=2e-4)


def test_quantity_is_non_increasing_in_price(response):
    assert response.multipliers == tuple(sorted(DEFAULT_MULTIPLIERS))
    assert np.all(np.diff(response.quantity, axis=0) <= TOL)  # ISO prices are positive: rows are in price order
    assert np.all(response.quantity <= response.raw + TOL)


def test_steps_are_few_nonzero_and_well_signed(response):
    curve = curve_of(response)
    assert len(curve) == 24
    for hour in curve:
        assert 0 < len(hour) <= MAX_BID_STEPS
        assert all(isinstance(s, BidStep) and s.quantity_mw != 0.0 for s in hour)


def test_higher_price_never_gives_a_larger_award(case, response):
    curve = curve_of(response)
    iso = np.asarray(case.grid.iso_price)
    levels = sorted({*np.linspace(0.2, 3.0, 29), *response.multipliers})
    awards = np.array([cleared(curve, m * iso) for m in levels])
    assert np.all(np.diff(awards, axis=0) <= TOL)


def test_bid_curve_at_one_price_level_bids_the_same_solve(case, response):
    """bid_curve is price_response then curve_of; its one solve here repeats the verified one at the ISO price."""
    curve = bid_curve(case, case.grid.iso_price, subperiods=1, multipliers=(1.0,))
    k = response.multipliers.index(1.0)
    np.testing.assert_allclose(cleared(curve, case.grid.iso_price), response.raw[k], atol=TOL)
    assert all(len(hour) <= 1 for hour in curve)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(1.0, 200.0), st.floats(-20.0, 20.0)), min_size=1, max_size=MAX_BID_STEPS))
def test_hour_steps_clear_each_price_at_its_quantity(points):
    prices = np.array([p for p, _ in points])
    quantity = monotone(prices[:, None], np.round(np.array([q for _, q in points]), 6)[:, None])[:, 0]
    steps = hour_steps(prices, quantity)
    assert len(steps) <= len(points)
    curve = (steps,) + ((),) * 23
    for p, q in zip(prices, quantity):
        assert cleared(curve, [float(p)] + [0.0] * 23)[0] == pytest.approx(q, abs=TOL)


def test_monotone_fix_takes_a_running_minimum_in_price_order():
    prices = np.array([[10.0, -10.0, 0.0], [20.0, -20.0, 0.0], [30.0, -30.0, 0.0]])
    raw = np.array([[5.0, 1.0, 3.0], [6.0, 2.0, 1.0], [4.0, 3.0, 2.0]])
    fixed = monotone(prices, raw)
    np.testing.assert_array_equal(fixed[:, 0], [5.0, 5.0, 4.0])
    np.testing.assert_array_equal(fixed[:, 1], [1.0, 2.0, 3.0])  # negative ISO price: row 2 is the cheapest
    np.testing.assert_array_equal(fixed[:, 2], [1.0, 1.0, 1.0])  # one price, one quantity
    with pytest.raises(ValueError, match="non-increasing"):
        hour_steps(np.array([1.0, 2.0]), np.array([1.0, 2.0]))


def test_forecast_scenario_is_the_mean_of_the_sampled_errors(case):
    f = forecast_scenario(case, 2)
    s = sample(case, 4000, 2, island_hours=0, seed=5)
    assert f.S == 1 and np.all(f.connected == 1)
    np.testing.assert_allclose(f.load[0], np.repeat(case.fixed_load.forecast, 2))
    np.testing.assert_allclose(f.renewable[:, 0], s.renewable.mean(axis=1), atol=0.01)
    e = np.random.default_rng(0).uniform(-1, 1, 400_000)
    assert clipped_mean(np.array([0.9]), 0.3, 1.0)[0] == pytest.approx(np.minimum(0.9 * (1 + 0.3 * e), 1.0).mean(),
                                                                      abs=1e-3)


@pytest.mark.parametrize("multipliers", [(), (0.0, 1.0), (1.0, float("nan")), tuple(np.linspace(0.1, 3, 17))])
def test_bad_multipliers_are_refused_before_solving(case, multipliers):
    with pytest.raises(ValueError, match="multiplier"):
        price_response(case, case.grid.iso_price, multipliers=multipliers)
