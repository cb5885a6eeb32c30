"""Clearing: hand-worked cases of docs/market.md and property tests of its rules."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmo.market.clearing import BidCurve, ClearingResult, Step, clear, fixed_awards
from scenarios.horizon import HOURS

TOL = 1e-9


def one_hour(agent: str, steps: list[tuple[float, float]], hour: int = 0) -> BidCurve:
    """A bid with ``steps`` in one hour and nothing in the others."""
    return BidCurve(agent, tuple(tuple(Step(p, q) for p, q in steps) if h == hour else () for h in range(HOURS)))


def at(result: ClearingResult, hour: int = 0) -> dict[str, float]:
    return {a: v[hour] for a, v in result.awards.items()}


# --- hand cases -------------------------------------------------------------------------------------------------

def test_no_congestion_price_is_iso_and_awards_follow_bids():
    bids = [one_hour("mg1", [(80, 4), (50, 3), (30, 2)]),  # buys 4 + 3; the step at 30 < ISO is rejected
            one_hour("mg2", [(40, 1)])]                       # priced exactly at ISO: accepted
    r = clear(bids, 40, 20, 20)
    assert r.price[0] == 40 and r.congested[0] == "none"
    assert at(r) == {"mg1": 7.0, "mg2": 1.0}
    assert r.price[1:] == (40.0,) * 23 and r.congested[1:] == ("none",) * 23
    assert all(v == 0.0 for a in r.awards.values() for v in a[1:])


def test_import_congestion_price_rises_to_marginal_bid_and_total_is_limit():
    bids = [one_hour("mg1", [(100, 6)]), one_hour("mg2", [(70, 5)]), one_hour("mg3", [(55, 4)])]
    r = clear(bids, 40, 8, 20)
    # At 40 or 55 the feeder would import 15 or 11 > 8; at 70 the 6 MW above 70 plus up to 5 MW at 70 fit.
    assert r.price[0] == 70 and r.congested[0] == "import"
    assert at(r) == {"mg1": 6.0, "mg2": 2.0, "mg3": 0.0}
    assert r.net_import(0) == 8.0


def test_import_congestion_lowest_price_when_the_limit_is_met_exactly():
    # Rejecting the 5 MW at 60 meets the limit exactly: any price in [60, 100) clears; the lowest, 60, is chosen.
    r = clear([one_hour("mg1", [(100, 10), (60, 5)])], 40, 10, 0)
    assert r.price[0] == 60 and at(r) == {"mg1": 10.0}


def test_import_congestion_draws_in_local_supply():
    # A local seller at 60 (above ISO) is accepted once congestion lifts the price past its offer.
    r = clear([one_hour("mg1", [(100, 10)]), one_hour("mg2", [(60, -3)])], 40, 5, 0)
    assert r.price[0] == 100 and r.congested[0] == "import"
    assert at(r) == {"mg1": 8.0, "mg2": -3.0}


def test_export_congestion_price_falls_to_marginal_offer():
    bids = [one_hour("mg1", [(10, -3)]), one_hour("mg2", [(25, -4)]), one_hour("mg3", [(35, -5)])]
    r = clear(bids, 40, 20, 6)
    # At 40 or 35 exports would be 12 or 7 > 6; at 25 the 3 MW below 25 plus up to 4 MW at 25 fit.
    assert r.price[0] == 25 and r.congested[0] == "export"
    assert at(r) == {"mg1": -3.0, "mg2": -3.0, "mg3": 0.0}
    assert r.net_import(0) == -6.0


def test_pro_rata_tie_at_the_margin():
    bids = [one_hour("mg1", [(80, 6)]), one_hour("mg2", [(80, 4)]), one_hour("mg3", [(90, 1)])]
    r = clear(bids, 40, 6, 0)
    assert r.price[0] == 80
    assert at(r) == pytest.approx({"mg1": 3.0, "mg2": 2.0, "mg3": 1.0}, abs=TOL)


def test_tie_at_the_iso_price_is_rationed_without_a_price_rise():
    r = clear([one_hour("mg1", [(40, 6)]), one_hour("mg2", [(40, 2)])], 40, 4, 0)
    assert r.price[0] == 40 and r.congested[0] == "import"
    assert at(r) == pytest.approx({"mg1": 3.0, "mg2": 1.0}, abs=TOL)


def test_marginal_buyers_and_sellers_maximise_volume():
    # At 80 both a purchase (6) and a sale (4) are marginal; net must be 1: the sale is taken whole, 5 bought.
    bids = [one_hour("mg1", [(80, 6)]), one_hour("mg2", [(80, -4)])]
    r = clear(bids, 40, 1, 0)
    assert r.price[0] == 80 and at(r) == pytest.approx({"mg1": 5.0, "mg2": -4.0}, abs=TOL)


def test_local_sales_offset_local_purchases():
    bids = [one_hour("mg1", [(50, 10)]), one_hour("mg2", [(30, -4)])]
    r = clear(bids, 40, 6, 0)  # 10 - 4 = 6 fits the import limit exactly
    assert r.price[0] == 40 and r.congested[0] == "none"
    assert at(r) == {"mg1": 10.0, "mg2": -4.0}


def test_zero_limits_clear_a_local_market():
    bids = [one_hour("mg1", [(70, 5)]), one_hour("mg2", [(50, -3)])]
    r = clear(bids, 40, 0, 0)
    assert r.price[0] == 70 and at(r) == {"mg1": 3.0, "mg2": -3.0} and r.net_import(0) == 0.0


def test_hourly_limits_and_prices():
    bid = BidCurve("mg1", tuple((Step(100, 5),) for _ in range(HOURS)))
    limits = [5.0] * 12 + [2.0] * 12
    r = clear([bid], list(range(HOURS)), limits, 0)
    assert r.awards["mg1"] == (5.0,) * 12 + (2.0,) * 12
    assert r.price == tuple(float(h) for h in range(12)) + (100.0,) * 12


def test_agents_without_bids_get_zero_awards_and_results_are_sorted():
    r = clear([one_hour("mg2", [(50, 1)])], 40, 10, 10, agents=["mg3", "mg1"])
    assert list(r.awards) == ["mg1", "mg2", "mg3"]
    assert r.awards["mg1"] == r.awards["mg3"] == (0.0,) * HOURS


def test_every_agent_faces_the_uniform_price():
    r = clear([one_hour("mg1", [(50, 1)])], 40, 0.5, 10, agents=["mg2"])
    assert r.agent_price == {"mg1": r.price, "mg2": r.price} and r.price[0] == 50.0


def test_fixed_mode_publishes_given_awards_at_iso_price():
    table = [float(h % 7) - 1.5 for h in range(HOURS)]
    r = fixed_awards({"mg1": table}, 42.0)
    assert r.awards == {"mg1": tuple(table)}
    assert r.price == (42.0,) * HOURS and r.congested == ("none",) * HOURS


@pytest.mark.parametrize("call, reason", [
    (lambda: Step(float("nan"), 1), "finite"),
    (lambda: Step(10, float("inf")), "finite"),
    (lambda: BidCurve("", ((),) * HOURS), "non-empty"),
    (lambda: BidCurve("mg1", ((),) * 23), "24 hours"),
    (lambda: clear([], [40] * 23, 1, 1), "24 hourly"),
    (lambda: clear([], 40, -1, 1), ">= 0"),
    (lambda: clear([], 40, 1, float("inf")), "finite"),
    (lambda: clear([], float("nan"), 1, 1), "finite"),
    (lambda: clear([one_hour("mg1", []), one_hour("mg1", [])], 40, 1, 1), "more than one bid"),
    (lambda: fixed_awards({"mg1": [1.0] * 24}, [40] * 25), "24 hourly"),
    (lambda: fixed_awards({"mg1": [float("nan")] * 24}, 40), "finite"),
])
def test_invalid_input_is_rejected_with_a_one_line_reason(call, reason):
    with pytest.raises(ValueError, match=reason) as e:
        call()
    assert "\n" not in str(e.value)


# --- properties -------------------------------------------------------------------------------------------------

AGENTS = ("mg1", "mg2", "mg3", "mg4")
# Few distinct prices, so ties at the margin and at the ISO price are common.
prices = st.integers(0, 12).map(lambda p: 10.0 * p)
quantities = st.one_of(st.integers(-8, 8).map(float),
                       st.floats(-8, 8, allow_nan=False, allow_infinity=False, allow_subnormal=False))
steps = st.lists(st.builds(Step, prices, quantities), max_size=3).map(tuple)


@st.composite
def markets(draw):
    agents = draw(st.lists(st.sampled_from(AGENTS), min_size=1, max_size=4, unique=True))
    # Most hours empty keeps examples small; the busy hours carry the interesting books.
    busy = draw(st.sets(st.integers(0, HOURS - 1), min_size=1, max_size=3))
    bids = [BidCurve(a, tuple(draw(steps) if h in busy else () for h in range(HOURS))) for a in agents]
    iso = draw(st.lists(prices, min_size=HOURS, max_size=HOURS))
    imp = draw(st.lists(st.integers(0, 12).map(float), min_size=HOURS, max_size=HOURS))
    exp = draw(st.lists(st.integers(0, 12).map(float), min_size=HOURS, max_size=HOURS))
    return bids, iso, imp, exp


def _steps_of(bid: BidCurve, hour: int) -> list[Step]:
    return [s for s in bid.hours[hour] if s.quantity != 0]


def _bounds(steps: list[Step], p: float) -> tuple[float, float]:
    """The least and greatest award consistent with price p: strictly in-the-money steps in full, steps at p
    anywhere between none and all, out-of-the-money steps not at all."""
    lo = math.fsum(s.quantity for s in steps if (s.quantity > 0 and s.price > p) or (s.quantity < 0 and s.price <= p))
    hi = math.fsum(s.quantity for s in steps if (s.quantity > 0 and s.price >= p) or (s.quantity < 0 and s.price < p))
    return lo, hi


@settings(max_examples=40, deadline=None)
@given(markets())
def test_limits_hold_and_price_matches_congestion(market):
    bids, iso, imp, exp = market
    r = clear(bids, iso, imp, exp)
    for h in range(HOURS):
        x = r.net_import(h)
        assert -exp[h] - TOL <= x <= imp[h] + TOL
        if r.congested[h] == "none":
            assert r.price[h] == iso[h]
        elif r.congested[h] == "import":
            assert r.price[h] >= iso[h] and x == pytest.approx(imp[h], abs=1e-7)
        else:
            assert r.price[h] <= iso[h] and x == pytest.approx(-exp[h], abs=1e-7)


@settings(max_examples=40, deadline=None)
@given(markets())
def test_awards_are_consistent_with_each_bid_curve(market):
    bids, iso, imp, exp = market
    r = clear(bids, iso, imp, exp)
    for b in bids:
        for h in range(HOURS):
            s = _steps_of(b, h)
            award = r.awards[b.agent][h]
            buy = math.fsum(x.quantity for x in s if x.quantity > 0)
            sell = math.fsum(x.quantity for x in s if x.quantity < 0)
            assert sell - TOL <= award <= buy + TOL
            lo, hi = _bounds(s, r.price[h])
            assert lo - 1e-7 <= award <= hi + 1e-7


@settings(max_examples=40, deadline=None)
@given(markets())
def test_congested_price_is_the_least_move_from_iso(market):
    """No price nearer the ISO price could have met the limit (docs/market.md, "Price")."""
    bids, iso, imp, exp = market
    r = clear(bids, iso, imp, exp)
    for h in range(HOURS):
        s = [x for b in bids for x in _steps_of(b, h)]
        p = r.price[h]
        nearer = {iso[h], *(x.price for x in s)}
        if r.congested[h] == "import":
            for q in (q for q in nearer if iso[h] <= q < p):
                assert _bounds(s, q)[0] > imp[h]
        if r.congested[h] == "export":
            for q in (q for q in nearer if p < q <= iso[h]):
                assert _bounds(s, q)[1] < -exp[h]


@settings(max_examples=30, deadline=None)
@given(markets(), st.data())
def test_permuting_agents_and_steps_changes_nothing(market, data):
    bids, iso, imp, exp = market
    r = clear(bids, iso, imp, exp)
    shuffled = [BidCurve(b.agent, tuple(tuple(data.draw(st.permutations(steps))) for steps in b.hours))
                for b in data.draw(st.permutations(bids))]
    again = clear(shuffled, iso, imp, exp)
    assert repr(again) == repr(r)  # bit-identical (repr tells -0.0 from 0.0, == does not)
    assert repr(clear(bids, iso, imp, exp)) == repr(r)


def test_a_price_of_minus_zero_clears_as_zero_whatever_the_order():
    """Sells of 4 MW at -0.0 and at 0.0 $/MWh against an export limit of 4 MW: the price is the one 0.0."""
    sells = [one_hour("mg1", [(-0.0, -4.0)]), one_hour("mg2", [(0.0, -4.0)])]
    results = [clear(order, 1.0, 10.0, 4.0) for order in (sells, sells[::-1])]
    assert [repr(r.price[0]) for r in results] == ["0.0", "0.0"] and results[0].congested[0] == "export"
    assert repr(results[0]) == repr(results[1])
    assert repr(clear([], -0.0, 1.0, 1.0).price[0]) == "0.0"


def test_large_book_clears_quickly_and_exactly():
    """A 200-agent book: the limit binds and is met to rounding, well inside the test budget."""
    bids = [BidCurve(f"mg{i}", tuple((Step(40 + (i * 7 + h) % 50, 1 + i % 3), Step(30 + i % 20, -0.5))
                                for h in range(HOURS))) for i in range(200)]
    r = clear(bids, 45, 100, 100)
    assert all(c == "import" for c in r.congested)
    assert all(abs(r.net_import(h) - 100) < 1e-9 for h in range(HOURS))
