"""The ISO's curve at the substation (docs/market.md, "The ISO's curve"): hand cases, the equilibrium it clears at,
the flat curve as today's clearing bit for bit, and the copper plate on a curve as the LP's optimum."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_distflow import LOOSE, kkt
from test_distflow import markets as feeder_markets
from test_distflow import network_limits_hold, random_book

from dmo.market.clearing import BidCurve, IsoCurve, Step, clear, segments
from dmo.market.distflow import clear_network, hour_program
from scenarios.horizon import HOURS
from scenarios.network import load_network

TOL = 1e-9


def one_hour(agent: str, steps: list[tuple[float, float]]) -> BidCurve:
    return BidCurve(agent, tuple(tuple(Step(p, q) for p, q in steps) if h == 0 else () for h in range(HOURS)))


def first(result) -> tuple[float, str, dict[str, float]]:
    return result.price[0], result.congested[0], {a: v[0] for a, v in result.awards.items()}


# --- hand cases -------------------------------------------------------------------------------------------------

UP = IsoCurve(import_curve=((4.0, 0.0), (2.0, 15.0)))


def test_a_position_in_the_second_import_block_pays_its_premium():
    # At 40 the bids want 7 MW > 4; at 55 they want 5: inside the second block [4, 6], so 55 it is.
    bids = [one_hour("mg1", [(100, 5)]), one_hour("mg2", [(50, 2)])]
    assert first(clear(bids, 40, 20, 20, curve=UP)) == (55.0, "none", {"mg1": 5.0, "mg2": 0.0})


def test_between_two_blocks_a_bid_sets_the_price_and_it_is_not_congestion():
    # At 55 the bids want 4 MW, exactly the first block: the price rises from 40 to the marginal bid's 50 only.
    bids = [one_hour("mg1", [(100, 4)]), one_hour("mg2", [(50, 2)])]
    assert first(clear(bids, 40, 20, 20, curve=UP)) == (50.0, "none", {"mg1": 4.0, "mg2": 0.0})


def test_a_bid_at_a_blocks_price_is_served_by_that_block():
    # At 55 the ISO is indifferent across its second block: volume is maximised, as at the ISO price (docs/market.md)
    bids = [one_hour("mg1", [(100, 4)]), one_hour("mg2", [(55, 2)])]
    assert first(clear(bids, 40, 20, 20, curve=UP)) == (55.0, "none", {"mg1": 4.0, "mg2": 2.0})


def test_past_the_last_block_is_import_congestion():
    bids = [one_hour("mg1", [(100, 5)]), one_hour("mg2", [(80, 3)])]
    assert first(clear(bids, 40, 20, 20, curve=UP)) == (80.0, "import", {"mg1": 5.0, "mg2": 1.0})


def test_the_limit_cuts_the_blocks():
    bids = [one_hour("mg1", [(100, 5)]), one_hour("mg2", [(80, 3)])]
    # the limit cuts the second block to [4, 5]: mg1 alone fills it, and the lowest price that keeps mg2 out is 80
    assert first(clear(bids, 40, 5.0, 20, curve=UP)) == (80.0, "import", {"mg1": 5.0, "mg2": 0.0})


def test_exports_beyond_the_first_block_are_bought_at_a_discount():
    # The ISO buys 3 MW at 40 and 2 more at 30: the 4 MW sold clear at 30, and the offer at 35 is left out.
    down = IsoCurve(export_curve=((3.0, 0.0), (2.0, 10.0)))
    bids = [one_hour("mg1", [(20, -4)]), one_hour("mg2", [(35, -2)])]
    assert first(clear(bids, 40, 20, 20, curve=down)) == (30.0, "none", {"mg1": -4.0, "mg2": 0.0})


def test_a_spread_between_buying_and_selling_leaves_a_local_market():
    # The ISO sells at 50 and buys at 30: a buyer at 45 and a seller at 35 trade with each other at a bid's price.
    spread = IsoCurve(import_curve=((10.0, 10.0),), export_curve=((10.0, 10.0),))
    bids = [one_hour("mg1", [(45, 2)]), one_hour("mg2", [(35, -2)])]
    price, congested, awards = first(clear(bids, 40, 20, 20, curve=spread))
    assert 35 <= price <= 45 and congested == "none" and awards == {"mg1": 2.0, "mg2": -2.0}


def test_segments_merge_the_iso_price_and_cost_each_mw_at_its_block():
    seg = segments(IsoCurve(((4.0, 0.0), (2.0, 15.0)), ((3.0, 0.0), (2.0, 10.0))), 40.0, 5.0, 20.0)
    assert seg.price.tolist() == [30.0, 40.0, 55.0]
    assert seg.low.tolist() == [-5.0, -3.0, 4.0] and seg.high.tolist() == [-3.0, 4.0, 5.0]
    assert seg.cost(5.0) == 4 * 40 + 1 * 55 and seg.cost(-4.0) == -(3 * 40 + 1 * 30) and seg.cost(0.0) == 0
    flat = segments(IsoCurve(), 40.0, 5.0, 3.0)
    assert (flat.price.tolist(), flat.low.tolist(), flat.high.tolist()) == ([40.0], [-3.0], [5.0])
    assert flat.cost(0.1 + 0.2) == 40.0 * (0.1 + 0.2)  # exactly today's iso * P0


@pytest.mark.parametrize("curve, reason", [
    (dict(import_curve=((0.0, 0.0),)), "import_curve: every block must have MW > 0"),
    (dict(export_curve=((1.0, 5.0), (1.0, 5.0))), "export_curve: the discounts must be >= 0 and strictly"),
    (dict(import_curve=((1.0, -1.0),)), "import_curve: the premiums must be >= 0"),
    (dict(import_curve=((1.0, float("nan")),)), "import_curve price"),
    (dict(import_curve=((1.0, 0.0),) * 51), "import_curve: at most 50 blocks"),
])
def test_a_curve_that_is_not_one_is_refused_in_one_line(curve, reason):
    with pytest.raises(ValueError, match=reason.replace("(", r"\(")) as err:
        IsoCurve(**curve)
    assert "\n" not in str(err.value)


# --- properties -------------------------------------------------------------------------------------------------

def on_the_curve(seg, price: float, p0: float, congested: str) -> None:
    """The ISO's side of an equilibrium at ``price`` with the DMO at ``p0``: every block priced below the price is
    taken whole, none priced above it is touched (but at the curve's ends, the congested hours)."""
    cheaper, dearer = seg.price < price, seg.price > price
    assert p0 >= seg.high[cheaper].max(initial=-np.inf) - TOL or congested == "export"
    assert p0 <= seg.low[dearer].min(initial=np.inf) + TOL or congested == "import"
    assert seg.bottom - TOL <= p0 <= seg.top + TOL
    assert (congested == "import") <= (p0 >= seg.top - TOL) and (congested == "export") <= (p0 <= seg.bottom + TOL)


blocks = st.lists(st.tuples(st.integers(1, 8).map(float), st.integers(0, 40).map(float)), max_size=3).map(
    lambda bs: tuple((mw, extra) for mw, extra in zip([b[0] for b in bs], sorted({b[1] for b in bs}))))
curves = st.builds(IsoCurve, blocks, blocks)


@settings(max_examples=60, deadline=None)
@given(feeder_markets(), curves)
def test_every_hour_clears_at_an_equilibrium_of_the_bids_and_the_curve(market, curve):
    bids, _, iso, imp, exp = market
    r = clear(bids, iso, imp, exp, curve=curve)
    for h in range(HOURS):
        on_the_curve(segments(curve, iso[h], imp[h], exp[h]), r.price[h], r.net_import(h), r.congested[h])


@settings(max_examples=40, deadline=None)
@given(feeder_markets())
def test_the_flat_curve_is_todays_clearing_bit_for_bit(market):
    bids, _, iso, imp, exp = market
    plain = clear(bids, iso, imp, exp)
    wide = IsoCurve(((max(imp) + 1.0, 0.0),), ((max(exp) + 1.0, 0.0),))  # blocks past the limits: cut to them
    for r in (clear(bids, iso, imp, exp, curve=IsoCurve()), clear(bids, iso, imp, exp, curve=wide)):
        assert repr((r.price, r.awards, r.congested)) == repr((plain.price, plain.awards, plain.congested))


@pytest.mark.slow  # a search solving 24 LPs an example, seconds long; the binding feeder below checks the same
@settings(max_examples=30, deadline=None)
@given(feeder_markets(), curves)
def test_on_a_curve_the_copper_plate_is_the_lps_optimum(market, curve):
    bids, where, iso, imp, exp = market
    r = clear_network(bids, LOOSE, where, iso, imp, exp, curve=curve)
    plate = clear(bids, iso, imp, exp, curve=curve)
    assert repr((r.price, r.awards, r.congested)) == repr((plate.price, plate.awards, plate.congested))
    for h in range(HOURS):
        lp = hour_program(bids, LOOSE, where, h, iso, imp, exp, curve=curve)
        assert -lp.objective == pytest.approx(r.welfare[h], rel=1e-9, abs=1e-6)


def test_on_a_binding_feeder_the_curve_prices_the_substation_and_kkt_holds():
    net = load_network("ieee33", power_factor=0.95)
    curve = IsoCurve(((3.5, 0.0), (0.5, 10.0), (0.5, 20.0), (0.5, 30.0), (3.0, 45.0)), ((1.0, 0.0), (1.0, 8.0)))
    bids, where = random_book(net, np.random.default_rng(3), 40, 0.15)
    r = clear_network(bids, net, where, 40.0, 6.0, 6.0, curve=curve)
    network_limits_hold(net, r)
    seg = segments(curve, 40.0, 6.0, 6.0)
    for h in range(HOURS):  # at a boundary of two blocks, the lines' duals set a price between their prices
        on_the_curve(seg, r.price[h], r.exchange_mw[h], r.congested[h])
    assert len(set(r.price) & set(seg.price)) >= 2  # the day meets more than one block
    for h in range(0, HOURS, 3):
        prog = hour_program(bids, net, where, h, 40.0, 6.0, 6.0, curve=curve)
        kkt(prog)
        assert -prog.objective == pytest.approx(r.welfare[h], rel=1e-9, abs=1e-6)
        assert prog.x[-len(seg.price):].sum() == pytest.approx(r.exchange_mw[h], abs=1e-7)
