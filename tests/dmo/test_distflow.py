"""Clearing on a feeder: hand cases of docs/market.md ("Clearing on a feeder"), the copper plate as its special case,
prices checked against the LP's KKT conditions and against finite differences of the welfare, order invariance; the
AC-faithful clearing's plan against pandapower's AC flow, and its last LP's KKT conditions and prices."""

from __future__ import annotations

import dataclasses
import math
from typing import get_args

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dmo.market.clearing import BidCurve, Step, clear
from dmo.market.distflow import FACETS, VOLL, NetworkClearing, clear_network, hour_program
from messages.schemas import PRICE_CAP, Congestion
from scenarios.horizon import HOURS
from scenarios.network import build, load_network
from test_clearing import AGENTS, prices, steps  # the copper plate's books: ties at the margin common

TOL = 1e-9
WIDE = 1e6  # substation limits that never bind


def one_hour(agent: str, steps: list[tuple[float, float]], hour: int = 0) -> BidCurve:
    return BidCurve(agent, tuple(tuple(Step(p, q) for p, q in steps) if h == hour else () for h in range(HOURS)))


def at(result, hour: int = 0) -> dict[str, float]:
    return {a: v[hour] for a, v in result.awards.items()}


def chain(n: int, *, r_ohm: float = 0.01, x_ohm: float = 0.01, s_max: float = 1e4, load: float = 0.0,
          v_min: float = 0.5, v_max: float = 1.5, power_factor: float = 1.0, base_kv: float = 10.0):
    """A feeder 0-1-...-(n-1): by default unloaded, with lines and voltage limits that never bind."""
    buses = [{"name": str(b), "p_mw": load if b else 0.0, "q_mvar": 0.0} for b in range(n)]
    lines = [{"from": str(b), "to": str(b + 1), "r_ohm": r_ohm, "x_ohm": x_ohm, "s_max_mva": s_max}
             for b in range(n - 1)]
    return build(f"chain{n}", base_kv, buses, lines, "0", power_factor=power_factor, v_min=v_min, v_max=v_max,
                 load_profile=(1.0,) * HOURS)


def network_limits_hold(net, r: NetworkClearing, tol: float = 1e-7) -> None:
    facet = FACETS[:, :1, None] * r.flow_p.T[None] + FACETS[:, 1:, None] * r.flow_q.T[None]  # 8 x lines x hours
    assert (facet <= net.s_max_mva[None, :, None] + tol).all()
    feeder = np.arange(net.n_buses) != net.root
    assert (r.voltage_pu[:, feeder] ** 2 >= net.v_min[feeder] ** 2 - tol).all()
    assert (r.voltage_pu[:, feeder] ** 2 <= net.v_max[feeder] ** 2 + tol).all()


def awards_follow_prices(bids, r: NetworkClearing, tol: float = 1e-7) -> None:
    """Each agent's award lies between what its steps strictly in the money at its price call for and what they
    call for with its steps at the price accepted too."""
    for b in bids:
        for h in range(HOURS):
            p = r.agent_price[b.agent][h]
            buy = [x for x in b.hours[h] if x.quantity > 0]
            sell = [x for x in b.hours[h] if x.quantity < 0]
            lo = math.fsum([x.quantity for x in buy if x.price > p] + [x.quantity for x in sell if x.price <= p])
            hi = math.fsum([x.quantity for x in buy if x.price >= p] + [x.quantity for x in sell if x.price < p])
            assert lo - tol <= r.awards[b.agent][h] <= hi + tol, (b.agent, h, p)


# --- hand cases -----------------------------------------------------------------------------------------------

def test_a_congested_line_raises_the_price_behind_it_to_the_marginal_local_bid():
    # feeder5's line 2-3 is rated 3 MVA; bus 3's buyer wants 5 MW at $90, its seller offers 1 MW at $70.
    net = load_network("feeder5")
    bids = [one_hour("far", [(90, 5)]), one_hour("seller", [(70, -1)]), one_hour("near", [(60, 1)])]
    r = clear_network(bids, net, {"far": "3", "seller": "3", "near": "1"}, 40, WIDE, WIDE)
    b3 = net.index["3"]
    line = int(net.line_to[b3])
    assert r.congested[0] == "line" and r.lines_binding[0] == (line,)
    assert r.price[0] == 40.0  # the energy price: the substation is not constrained
    assert r.agent_price["far"][0] == 90.0 and r.agent_price["near"][0] == 40.0
    # The line carries bus 3's fixed Q (power factor 1 for the microgrids), so the octagon's facet P + tan(pi/8) Q
    # <= 3 binds: P = 3 - tan(pi/8) Q reaches bus 3, and with the seller's 1 MW the buyer gets P + 1 - fixed load.
    p_line = 3.0 - math.tan(math.pi / 8) * net.fixed_q[0, b3]
    assert r.flow_p[0, line] == pytest.approx(p_line, abs=1e-9)
    assert at(r)["far"] == pytest.approx(p_line + 1 - net.fixed_p[0, b3], abs=1e-9)
    assert at(r)["seller"] == -1.0 and at(r)["near"] == 1.0
    assert r.congestion[0, b3] == pytest.approx(50.0, abs=1e-9) and r.voltage[0, b3] == pytest.approx(0.0, abs=1e-9)
    assert r.buses_binding[0] == () and r.shed_mw.sum() == 0.0
    # what binds: facet 0 (P + tan(pi/8) Q) of that line alone, at a limit loading of 1, worth the congestion's $50
    # per MW of rating (the far bus's MW moves the facet by 1)
    assert r.binding_facet[0, line] == 0 and (np.delete(r.binding_facet[0], line) == -1).all()
    assert r.limit_loading[0, line] == pytest.approx(1.0, abs=1e-12) and r.line_shadow_price[0, line] == 50.0
    assert math.hypot(r.flow_p[0, line], r.flow_q[0, line]) / net.s_max_mva[line] < 1.0  # |S| under the circle


def test_a_voltage_limit_prices_the_far_bus():
    # One line of 1 ohm at 10 kV (r = 0.01 p.u.): U = 1 - 0.02 P >= 0.95^2 caps the far bus's import at 4.875 MW.
    net = chain(2, r_ohm=1.0, x_ohm=0.0, v_min=0.95)
    bids = [one_hour("mg", [(100, 3), (80, 3), (60, 3)])]
    r = clear_network(bids, net, {"mg": "1"}, 40, WIDE, WIDE)
    cap = (1 - 0.95 ** 2) / 0.02
    assert r.congested[0] == "voltage" and r.buses_binding[0] == (1,) and r.lines_binding[0] == ()
    assert r.agent_price["mg"][0] == 80.0 and r.price[0] == 40.0
    assert at(r)["mg"] == pytest.approx(cap, abs=1e-9) and r.voltage_pu[0, 1] == pytest.approx(0.95, abs=1e-9)
    assert r.voltage[0, 1] == pytest.approx(40.0, abs=1e-9) and r.congestion[0, 1] == 0.0
    # its dual: $40 per MW at 0.02 p.u. of U per MW is $2,000 per p.u. of U, 2 x 0.95 x 2,000 per p.u. of V
    assert r.binding_voltage[0].tolist() == [0, -1] and r.binding_facet[0].tolist() == [-1]
    assert r.voltage_shadow_price[0, 1] == pytest.approx(3800.0, rel=1e-9)


def test_a_voltage_margin_holds_lindistflow_inside_the_narrowed_band():
    net = chain(2, r_ohm=1.0, x_ohm=0.0, v_min=0.95)
    bids = [one_hour("mg", [(100, 3), (80, 3), (60, 3)])]
    r = clear_network(bids, net, {"mg": "1"}, 40, WIDE, WIDE, margin=0.01)
    assert r.voltage_pu[0, 1] == pytest.approx(0.96, abs=1e-9) and r.buses_binding[0] == (1,)
    assert at(r)["mg"] == pytest.approx((1 - 0.96 ** 2) / 0.02, abs=1e-9) and r.agent_price["mg"][0] == 80.0


def test_fixed_load_beyond_the_import_limit_is_shed_at_voll_and_reported():
    net = chain(3, load=2.0)  # 2 MW at each of buses 1 and 2, 4 MW in all, behind a 3 MW import limit
    r = clear_network([one_hour("mg", [(50, 1)])], net, {"mg": "2"}, 40, 3.0, 0.0)
    assert r.congested[0] == "import" and r.price[0] == VOLL == PRICE_CAP
    assert math.fsum(r.shed_mw[0]) == pytest.approx(1.0, abs=1e-9) and at(r)["mg"] == 0.0
    assert r.exchange_mw[0] == pytest.approx(3.0, abs=1e-9)
    assert r.welfare[0] == pytest.approx(-40 * 3.0 - VOLL * 1.0, abs=1e-6)
    # an hour without a bid sheds too: the fixed load alone is beyond the limit
    assert r.congested[1] == "import" and r.price[1] == VOLL and math.fsum(r.shed_mw[1]) == pytest.approx(1.0)


def test_steps_tied_at_their_bus_price_share_the_line_pro_rata():
    # A 5 MW line: the buyer at $90 takes 1 MW, the two at $80 share the other 4 MW as 6 : 4, whatever the LP chose
    net = chain(2, s_max=5.0)
    bids = [one_hour("mg1", [(80, 6)]), one_hour("mg2", [(80, 4)]), one_hour("mg3", [(90, 1)])]
    r = clear_network(bids, net, {"mg1": "1", "mg2": "1", "mg3": "1"}, 40, WIDE, WIDE)
    assert r.agent_price["mg1"][0] == 80.0 and r.congested[0] == "line"
    assert at(r) == pytest.approx({"mg1": 2.4, "mg2": 1.6, "mg3": 1.0}, abs=TOL)


def test_with_q_the_octagon_bounds_the_apparent_power_from_inside_the_circle():
    # power factor 0.8: a microgrid importing P draws 0.75 P; the 45-degree-ish flow meets a facet, not the circle
    net = chain(2, s_max=5.0, power_factor=0.8)
    r = clear_network([one_hour("mg", [(100, 10), (50, 10)])], net, {"mg": "1"}, 40, WIDE, WIDE)
    p, q = r.flow_p[0, 0], r.flow_q[0, 0]
    assert q == pytest.approx(0.75 * p) and math.hypot(p, q) < 5.0
    assert max(FACETS @ (p, q)) == pytest.approx(5.0, abs=1e-9)
    assert r.congested[0] == "line" and r.agent_price["mg"][0] == 100.0


def test_the_congestion_labels_are_the_messages_literal():
    assert {"none", "import", "export", "line", "voltage"} == set(get_args(Congestion))


@pytest.mark.parametrize("call, reason", [
    (lambda net: clear_network([one_hour("mg1", [])], net, {"mg1": "9"}, 40, 1, 1), "no bus '9'"),
    (lambda net: clear_network([one_hour("mg1", [])], net, {"mg1": "0"}, 40, 1, 1), "substation"),
    (lambda net: clear_network([one_hour("mg1", [])], net, {}, 40, 1, 1), "mg1 has no bus"),
    (lambda net: clear_network([], net, {}, 40, 1, 1, agents=["mg2"]), "mg2 has no bus"),
    (lambda net: clear_network([], net, [], 40, 1, 1), "must map"),
    (lambda net: clear_network([], net, {}, 40, 1, 1, voll=0), "voll"),
    (lambda net: clear_network([], net, {}, 40, 1, 1, margin=-0.01), "voltage margin must be >= 0"),
    (lambda net: clear_network([], net, {}, 40, 1, 1, margin=0.05), "bus 1 has none left"),
    (lambda net: clear_network([], "feeder5", {}, 40, 1, 1), "Network"),
    (lambda net: clear_network([], net, {}, 40, -1, 1), ">= 0"),
    (lambda net: clear_network([one_hour("a", []), one_hour("a", [])], net, {"a": "1"}, 40, 1, 1), "more than one"),
    (lambda net: clear_network([], net, {}, 40, 1, 1, method="acopf"), "method must be one of lindistflow, ac"),
])
def test_invalid_input_is_rejected_with_a_one_line_reason(call, reason):
    with pytest.raises(ValueError, match=reason) as e:
        call(load_network("feeder5"))
    assert "\n" not in str(e.value)


def test_a_feeder_that_cannot_be_served_even_unloaded_is_refused_in_one_line():
    net = build("high", 10.0, [{"name": "0"}, {"name": "1", "p_mw": 1.0, "v_min": 1.01, "v_max": 1.05}],
                [{"from": "0", "to": "1", "r_ohm": 0.1, "x_ohm": 0.1}], "0")  # held at 1.0 p.u., bus 1 needs 1.01
    with pytest.raises(ValueError, match="cannot clear even with every fixed load shed") as e:
        clear_network([], net, {}, 40, WIDE, WIDE)
    assert "\n" not in str(e.value)


def test_clearing_writes_nothing_on_stdout(capfd):
    net = load_network("feeder5")
    clear_network([one_hour("mg", [(90, 5)])], net, {"mg": "3"}, 40, WIDE, WIDE)  # an LP hour
    hour_program([one_hour("mg", [(90, 5)])], net, {"mg": "3"}, 0, 40, WIDE, WIDE)
    assert capfd.readouterr().out == ""


# --- the copper plate as the special case -----------------------------------------------------------------------



@st.composite
def markets(draw, buses=("1", "2", "3", "4")):
    agents = draw(st.lists(st.sampled_from(AGENTS), min_size=1, max_size=4, unique=True))
    busy = draw(st.sets(st.integers(0, HOURS - 1), min_size=1, max_size=3))
    bids = [BidCurve(a, tuple(draw(steps) if h in busy else () for h in range(HOURS))) for a in agents]
    where = {a: draw(st.sampled_from(buses)) for a in agents}
    iso = draw(st.lists(prices, min_size=HOURS, max_size=HOURS))
    imp = draw(st.lists(st.integers(0, 12).map(float), min_size=HOURS, max_size=HOURS))
    exp = draw(st.lists(st.integers(0, 12).map(float), min_size=HOURS, max_size=HOURS))
    return bids, where, iso, imp, exp


LOOSE = chain(5)


@settings(max_examples=40, deadline=None)
@given(markets())
def test_a_feeder_whose_limits_never_bind_clears_as_the_copper_plate_bit_for_bit(market):
    bids, where, iso, imp, exp = market
    r = clear_network(bids, LOOSE, where, iso, imp, exp)
    plate = clear(bids, iso, imp, exp)
    assert repr((r.price, r.awards, r.congested)) == repr((plate.price, plate.awards, plate.congested))
    assert r.agent_price == plate.agent_price
    assert (r.bus_price == np.array(plate.price)[:, None]).all() and not r.congestion.any() and not r.voltage.any()
    assert r.lines_binding == r.buses_binding == ((),) * HOURS and not r.shed_mw.any()


def test_with_fixed_load_the_copper_plate_clears_within_the_substation_limits_less_that_load():
    net = chain(4, load=0.5)  # 1.5 MW of fixed load
    bids = [one_hour("mg1", [(100, 3), (60, 2)]), one_hour("mg2", [(70, -1)])]
    r = clear_network(bids, net, {"mg1": "3", "mg2": "1"}, 40, 4.0, 0.0)
    plate = clear(bids, 40, 4.0 - 1.5, 1.5)
    assert repr((r.price, r.awards, r.congested)) == repr((plate.price, plate.awards, plate.congested))
    assert r.price[0] == 70.0 and r.exchange_mw[0] == pytest.approx(4.0)


@st.composite
def line_limited(draw):
    """Purchases (or sales) at distinct prices and a line limit falling strictly inside one of them."""
    n = draw(st.integers(1, 5))
    price = draw(st.lists(st.integers(1, 40).map(lambda p: 5.0 * p), min_size=n, max_size=n, unique=True))
    size = draw(st.lists(st.integers(1, 40).map(lambda q: q / 4), min_size=n, max_size=n))
    sell = draw(st.booleans())
    order = np.argsort(price)[::-1] if not sell else np.argsort(price)  # the order the limit fills them in
    k = draw(st.integers(0, n - 1))
    limit = sum(size[i] for i in order[:k]) + size[order[k]] * draw(st.sampled_from([0.25, 0.5, 0.75]))
    owners = draw(st.lists(st.sampled_from(AGENTS), min_size=n, max_size=n))
    bids = [BidCurve(a, tuple(tuple(Step(price[i], -size[i] if sell else size[i]) for i in range(n) if owners[i] == a)
                              if h == 0 else () for h in range(HOURS))) for a in sorted(set(owners))]
    iso = 0.0 if not sell else 300.0  # every step is in the money at the ISO price
    return bids, limit, iso


@settings(max_examples=40, deadline=None)
@given(line_limited())
def test_a_line_limit_clears_as_the_copper_plates_feeder_limit(case):
    bids, limit, iso = case
    net = chain(2, s_max=limit)
    r = clear_network(bids, net, {b.agent: "1" for b in bids}, iso, WIDE, WIDE)
    plate = clear(bids, iso, limit, limit)
    assert r.price[0] == iso and r.congested[0] == "line" and r.lines_binding[0] == (0,)
    assert [r.agent_price[a][0] for a in r.awards] == [plate.price[0]] * len(r.awards)
    assert r.awards.keys() == plate.awards.keys()
    for a in r.awards:
        assert r.awards[a][0] == pytest.approx(plate.awards[a][0], abs=TOL)
    assert abs(r.flow_p[0, 0]) == pytest.approx(limit, abs=TOL)


# --- prices that can be checked -----------------------------------------------------------------------------------

def random_book(net, rng, agents: int, scale: float, hours=range(HOURS)):
    buses = [b for b in net.buses if b != net.substation]
    where = {f"mg{i}": buses[int(rng.integers(len(buses)))] for i in range(agents)}
    bids = [BidCurve(a, tuple(tuple(Step(float(rng.uniform(10, 150)), float(rng.uniform(-0.4, 1.0)) * scale)
                                    for _ in range(3)) if h in hours else () for h in range(HOURS))) for a in where]
    return bids, where


def kkt(prog, tol: float = 1e-6) -> None:
    """Primal feasibility, stationarity and complementary slackness of the hour's LP, in scipy's signs."""
    x = prog.x
    assert np.abs(prog.A_eq @ x - prog.b_eq).max() <= tol
    slack = prog.b_ub - prog.A_ub @ x
    assert slack.min() >= -tol
    assert (x >= prog.lower - tol).all() and (x <= prog.upper + tol).all()
    assert (prog.ub_dual <= tol).all() and (prog.lower_dual >= -tol).all() and (prog.upper_dual <= tol).all()
    gradient = prog.c - prog.A_eq.T @ prog.eq_dual - prog.A_ub.T @ prog.ub_dual - prog.lower_dual - prog.upper_dual
    assert np.abs(gradient).max() <= tol * max(1.0, np.abs(prog.c).max())
    assert np.abs(prog.ub_dual * slack).max() <= tol
    finite_lo, finite_hi = np.isfinite(prog.lower), np.isfinite(prog.upper)
    assert np.abs(prog.lower_dual[finite_lo] * (x - prog.lower)[finite_lo]).max(initial=0) <= tol
    assert np.abs(prog.upper_dual[finite_hi] * (prog.upper - x)[finite_hi]).max(initial=0) <= tol


@pytest.mark.parametrize("name, agents, scale, limit", [("feeder5", 8, 2.0, 20.0), ("ieee33", 40, 0.15, 6.0)])
def test_every_hour_meets_the_kkt_conditions_with_lines_and_voltages_binding(name, agents, scale, limit):
    net = load_network(name, power_factor=0.95)
    rng = np.random.default_rng(7)
    lines = buses = 0
    for _ in range(3):
        bids, where = random_book(net, rng, agents, scale)
        r = clear_network(bids, net, where, 40.0, limit, limit)
        network_limits_hold(net, r)
        awards_follow_prices(bids, r)
        assert np.abs(r.energy[:, None] + r.congestion + r.voltage - r.bus_price).max() <= 1e-9
        for h in range(0, HOURS, 4):
            prog = hour_program(bids, net, where, h, 40.0, limit, limit)
            kkt(prog)
            assert -prog.objective == pytest.approx(r.welfare[h], rel=1e-9, abs=1e-6)
        lines += sum(map(bool, r.lines_binding))
        buses += sum(map(bool, r.buses_binding))
    assert lines and buses  # the books do bind both kinds of limit


def with_more_load(net, bus: int, hour: int, eps: float):
    """The network with ``eps`` MW (and tan(phi) eps Mvar: a microgrid's exchange) more fixed load at ``bus`` in
    ``hour``."""
    factor = net.load_profile[hour] * net.load_scale
    p, q = net.load_p_mw.copy(), net.load_q_mvar.copy()
    p[bus] += eps / factor
    q[bus] += net.tan_phi * eps / factor
    return dataclasses.replace(net, load_p_mw=p, load_q_mvar=q)


@pytest.mark.parametrize("name, agents, scale, limit, seed", [
    ("feeder5", 8, 2.0, 20.0, 0),  # three voltage limits bind
    ("feeder5", 8, 2.0, 20.0, 1),  # a line and a voltage limit
    ("ieee33", 40, 0.15, 6.0, 3),  # five lines and two voltage limits
])
def test_each_bus_price_is_the_welfare_lost_per_mw_of_load_there(name, agents, scale, limit, seed):
    net = load_network(name, power_factor=0.95)
    h, eps = 19, 1e-5
    bids, where = random_book(net, np.random.default_rng(seed), agents, scale, hours={h})  # continuous prices: no ties
    r = clear_network(bids, net, where, 40.0, limit, limit)
    assert r.lines_binding[h] or r.buses_binding[h]
    base = hour_program(bids, net, where, h, 40.0, limit, limit).objective
    for b in range(net.n_buses):
        more = hour_program(bids, with_more_load(net, b, h, eps), where, h, 40.0, limit, limit).objective
        assert (more - base) / eps == pytest.approx(r.bus_price[h, b], rel=1e-5, abs=1e-5), net.buses[b]


@pytest.mark.parametrize("method", ["lindistflow", "ac"])
@pytest.mark.parametrize("name, agents, scale, limit, seed", [
    ("feeder5", 8, 2.0, 20.0, 1),  # a line and a voltage limit
    ("ieee33", 40, 0.15, 6.0, 3),  # five lines and two voltage limits
])
def test_each_shadow_price_is_the_welfare_a_looser_limit_gains(name, agents, scale, limit, seed, method):
    """What binds is in the data: a binding line's limit loading is 1 and its shadow price is the welfare a MW more
    of its rating gains; a binding voltage's shadow price is the welfare 1 p.u. more room at its limit gains (finite
    differences of the hour's LP; on the AC flow, of the LP linearised at the plan, which moves with the limit)."""
    net = load_network(name, power_factor=0.95)
    h, eps = 19, 1e-6
    bids, where = random_book(net, np.random.default_rng(seed), agents, scale, hours={h})
    r = clear_network(bids, net, where, 40.0, limit, limit, method=method)
    lines, buses = np.flatnonzero(r.binding_facet[h] >= 0), np.flatnonzero(r.binding_voltage[h])
    assert lines.size and buses.size
    assert r.lines_binding[h] == tuple(lines) and r.buses_binding[h] == tuple(buses)
    assert np.abs(r.limit_loading[h, lines] - 1.0).max() <= 1e-6  # what a "limit_loading >= 1" query finds
    assert (r.limit_loading[h] <= 1.0 + 1e-6).all() and (r.line_shadow_price[h, r.binding_facet[h] < 0] == 0).all()
    assert (r.voltage_shadow_price[h, r.binding_voltage[h] == 0] == 0).all()
    base = hour_program(bids, net, where, h, 40.0, limit, limit, method=method).objective
    for line in lines[:3]:
        s_max = net.s_max_mva.copy()
        s_max[line] += eps
        looser = dataclasses.replace(net, s_max_mva=s_max)
        more = hour_program(bids, looser, where, h, 40.0, limit, limit, method=method).objective
        assert (base - more) / eps == pytest.approx(r.line_shadow_price[h, line], rel=1e-4, abs=1e-3), line
    for bus in buses[:2]:
        side = r.binding_voltage[h, bus]
        v = (net.v_max if side > 0 else net.v_min).copy()
        v[bus] += side * eps
        looser = dataclasses.replace(net, **{"v_max" if side > 0 else "v_min": v})
        more = hour_program(bids, looser, where, h, 40.0, limit, limit, method=method).objective
        assert (base - more) / eps == pytest.approx(r.voltage_shadow_price[h, bus], rel=1e-4, abs=1e-3), bus


# --- determinism ----------------------------------------------------------------------------------------------

def fingerprint(r: NetworkClearing) -> tuple:
    arrays = (r.bus_price, r.energy, r.congestion, r.voltage, r.flow_p, r.flow_q, r.voltage_pu, r.shed_mw)
    return (repr((r.price, r.awards, r.congested, r.agent_price, r.lines_binding, r.buses_binding, r.exchange_mw,
                  r.welfare)), tuple(a.tobytes() for a in arrays))


TIGHT = load_network("feeder5", power_factor=0.9)


@settings(max_examples=25, deadline=None)
@given(markets(), st.data())
def test_permuting_agents_and_steps_changes_nothing(market, data):
    bids, where, iso, imp, exp = market
    r = clear_network(bids, TIGHT, where, iso, imp, exp)
    shuffled = [BidCurve(b.agent, tuple(tuple(data.draw(st.permutations(steps))) for steps in b.hours))
                for b in data.draw(st.permutations(bids))]
    assert fingerprint(clear_network(shuffled, TIGHT, dict(reversed(where.items())), iso, imp, exp)) == fingerprint(r)
    network_limits_hold(TIGHT, r)
    awards_follow_prices(bids, r)


def test_a_bid_above_voll_behind_a_full_line_sheds_the_fixed_load_for_it():
    # 2 MW of fixed load behind a 3 MW line; a buyer at $150 outbids a value of lost load of $100
    net = chain(2, s_max=3.0, load=2.0)
    r = clear_network([one_hour("mg", [(150, 5)])], net, {"mg": "1"}, 40, WIDE, WIDE, voll=100.0)
    assert r.shed_mw[0, 1] == pytest.approx(2.0, abs=1e-9) and at(r)["mg"] == pytest.approx(3.0, abs=1e-9)
    assert r.agent_price["mg"][0] == 150.0 and r.congested[0] == "line"
    assert r.welfare[0] == pytest.approx(150 * 3 - 40 * 3 - 100 * 2, abs=1e-6)
    assert r.shed_mw[1, 1] == 0.0  # without the bid, serving the load is worth it
    kkt(hour_program([one_hour("mg", [(150, 5)])], net, {"mg": "1"}, 0, 40, WIDE, WIDE, voll=100.0))


# --- fair ties ------------------------------------------------------------------------------------------------

def star(trunk_mva: float = 3.0, lateral_mva: float = 1e4):
    """0-1, then 1-2 and 1-3: buses 2 and 3 sit behind the one trunk line 0-1, on twin laterals."""
    buses = [{"name": str(b), "p_mw": 0.0, "q_mvar": 0.0} for b in range(4)]
    lines = [{"from": "0", "to": "1", "r_ohm": 0.01, "x_ohm": 0.01, "s_max_mva": trunk_mva}] + [
        {"from": "1", "to": str(b), "r_ohm": 0.01, "x_ohm": 0.01, "s_max_mva": lateral_mva} for b in (2, 3)]
    return build("star", 10.0, buses, lines, "0", v_min=0.5, v_max=1.5, load_profile=(1.0,) * HOURS)


@pytest.mark.parametrize("method", ["lindistflow", "ac"])
def test_equal_bids_behind_one_full_line_share_it_equally_wherever_they_sit(method):
    # Two buyers at $90 for 5 MW behind a 3 MW trunk: the LP may give either one everything; the clearing gives
    # each half, on twin laterals or at one bus (less in AC there: one lateral carries both, with more losses)
    net = star()
    bids = [one_hour("a", [(90, 5)]), one_hour("b", [(90, 5)])]
    apart = clear_network(bids, net, {"a": "2", "b": "3"}, 40, WIDE, WIDE, method=method)
    swapped = clear_network(bids, net, {"a": "3", "b": "2"}, 40, WIDE, WIDE, method=method)
    together = clear_network(bids, net, {"a": "2", "b": "2"}, 40, WIDE, WIDE, method=method)
    for r in (apart, swapped, together):
        assert at(r)["a"] == pytest.approx(at(r)["b"], abs=1e-12) and r.congested[0] == "line"
        assert r.agent_price["a"][0] == r.agent_price["b"][0] == 90.0
    assert at(apart) == at(swapped)
    half = 1.5 if method == "lindistflow" else 1.49  # the trunk's 3 MW, less the laterals' losses in AC
    assert half - 0.01 < at(apart)["a"] <= 1.5 and at(together)["a"] <= at(apart)["a"]


@pytest.mark.parametrize("mw", [1.0, -1.0])
def test_a_step_at_exactly_its_bus_price_is_accepted_in_full_whether_or_not_another_line_binds(mw):
    # "m" buys (or sells) 1 MW at $40, the ISO's price, at bus 3. In hour 1 the copper plate clears: every step at
    # the price is accepted. In hour 2 a buyer at bus 2 fills lateral 1-2: the LP clears, and "m", still at its
    # bus's price of $40, is accepted in full again rather than wherever the LP's vertex left it.
    net = star(trunk_mva=1e4, lateral_mva=2.0)
    bids = [BidCurve("m", ((Step(40.0, mw),), (Step(40.0, mw),)) + ((),) * (HOURS - 2)),
            one_hour("far", [(90, 5)], hour=1)]
    r = clear_network(bids, net, {"m": "3", "far": "2"}, 40, WIDE, WIDE)
    assert r.congested[:2] == ("none", "line") and r.agent_price["m"][:2] == (40.0, 40.0)
    assert r.awards["m"][:2] == (mw, mw)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([60.0, 75.0, 90.0]), st.floats(0.1, 3.0), st.sampled_from(["2", "3"])),
                min_size=2, max_size=6), st.data())
def test_moving_equal_bids_between_equivalent_buses_changes_no_award(book, data):
    """Buses 2 and 3 of the star face the same limits (the trunk, the substation): moving any bid from one to the
    other, or permuting the agents, changes no award beyond 1e-9, and equal bids are awarded alike."""
    net = star(trunk_mva=4.0)
    bids = [one_hour(f"mg{i}", [(p, q)]) for i, (p, q, _) in enumerate(book)]
    where = {f"mg{i}": b for i, (_, _, b) in enumerate(book)}
    moved = {a: data.draw(st.sampled_from(["2", "3"])) for a in where}
    r = clear_network(bids, net, where, 40, WIDE, WIDE)
    again = clear_network(data.draw(st.permutations(bids)), net, moved, 40, WIDE, WIDE)
    for a in where:
        assert at(again)[a] == pytest.approx(at(r)[a], abs=1e-9), (a, where[a], moved[a])
    for i, (p, q, _) in enumerate(book):
        for j, (p2, q2, _) in enumerate(book):
            if p == p2:  # equal prices: equal shares of their quantities
                assert at(r)[f"mg{i}"] / q == pytest.approx(at(r)[f"mg{j}"] / q2, abs=1e-9)


# --- AC-faithful -----------------------------------------------------------------------------------------------

def microgrids(net, r: NetworkClearing, where) -> np.ndarray:
    """(24 x buses) the awards summed at their buses."""
    out = np.zeros((HOURS, net.n_buses))
    for agent, award in r.awards.items():
        out[:, net.index[where[agent]]] += award
    return out


@pytest.mark.slow  # pandapower
def test_the_ac_faithful_plan_keeps_every_limit_in_pandapowers_ac_flow_where_lindistflows_breaks_them():
    from dmo.market.acflow import check_hours

    net = load_network("ieee33", power_factor=0.95)
    bids, where = random_book(net, np.random.default_rng(7), 40, 0.15)
    broken = {}
    for method in ("lindistflow", "ac"):
        r = clear_network(bids, net, where, 40.0, 6.0, 6.0, method=method)
        assert not r.shed_mw.any()
        checks = check_hours(net, microgrids(net, r, where))
        v = np.array([c.v_pu for c in checks])
        excess = np.maximum(0.0, np.maximum(net.v_min - v, v - net.v_max).max(axis=1))
        broken[method] = int((excess > 1e-4).sum())
        assert max(c.max_loading for c in checks) <= 1.005
        # what the clearing says its plan breaks in AC is what pandapower finds
        assert np.abs(np.array(r.ac_voltage_excess_pu) - excess).max() <= 1e-8
    assert broken["lindistflow"] >= 12 and broken["ac"] == 0
    assert r.method == "ac" and all(1 <= k < 20 for k in r.iterations)
    assert max(r.ac_voltage_excess_pu) <= 1e-6 and max(r.ac_overload) <= 1e-6


@pytest.mark.parametrize("name, agents, scale, limit", [("feeder5", 8, 2.0, 20.0), ("ieee33", 40, 0.15, 6.0)])
def test_the_ac_faithful_clearings_last_lp_meets_the_kkt_conditions_and_its_four_components_add_up(
        name, agents, scale, limit):
    net = load_network(name, power_factor=0.95)
    bids, where = random_book(net, np.random.default_rng(11), agents, scale)
    r = clear_network(bids, net, where, 40.0, limit, limit, method="ac")
    # every hour's plan keeps every limit in its AC flow within the iterations' tolerance, those whose linearised
    # clearings alternated (here 1 and 3 of them) settled between their plans
    assert max(r.ac_voltage_excess_pu) <= 1e-6 and max(r.ac_overload) <= 1e-6
    assert max(r.iterations) > 10  # an hour settled
    awards_follow_prices(bids, r)
    parts = r.energy[:, None] + r.loss + r.congestion + r.voltage
    assert (np.abs(parts - r.bus_price) <= 1e-9 * np.maximum(1.0, np.abs(r.bus_price))).all()
    assert (r.loss[:, net.root] == 0).all() and (np.abs(r.loss[:, 1:]) > 0).all()  # every MW downstream moves losses
    lines = buses = 0
    for h in range(0, HOURS, 5):
        prog = hour_program(bids, net, where, h, 40.0, limit, limit, method="ac")
        kkt(prog)
        lines += bool(r.lines_binding[h])
        buses += bool(r.buses_binding[h])
    assert lines + buses  # a limit binds in some hour checked
    # the substation buys the loads and the plan's AC losses
    assert r.exchange_mw[0] > math.fsum(net.fixed_p[0] + microgrids(net, r, where)[0])
    shuffled = [BidCurve(b.agent, tuple(tuple(reversed(steps)) for steps in b.hours)) for b in reversed(bids)]
    assert fingerprint(clear_network(shuffled, net, dict(reversed(where.items())), 40.0, limit, limit,
                                     method="ac")) == fingerprint(r)


def lp_objective(prog, b_eq, b_ub) -> float:
    from scipy.optimize import linprog

    res = linprog(prog.c, A_ub=prog.A_ub, b_ub=b_ub, A_eq=prog.A_eq, b_eq=b_eq,
                  bounds=np.column_stack([prog.lower, prog.upper]), method="highs")
    assert res.status == 0, res.message
    return float(res.fun)


@pytest.mark.parametrize("name, agents, scale, limit, seed", [("feeder5", 8, 2.0, 20.0, 1), ("ieee33", 40, 0.15, 6.0, 3)])
def test_each_ac_bus_price_is_the_welfare_its_last_lp_loses_per_mw_of_a_microgrids_load_there(
        name, agents, scale, limit, seed):
    net = load_network(name, power_factor=0.95)
    h, eps = 19, 1e-5
    bids, where = random_book(net, np.random.default_rng(seed), agents, scale, hours={h})
    r = clear_network(bids, net, where, 40.0, limit, limit, method="ac")
    assert r.lines_binding[h] or r.buses_binding[h]
    prog = hour_program(bids, net, where, h, 40.0, limit, limit, method="ac")
    base = lp_objective(prog, prog.b_eq, prog.b_ub)
    assert base == pytest.approx(prog.objective, rel=1e-9, abs=1e-9)
    for b in range(net.n_buses):  # eps MW of a microgrid's import at b, fixed: its column moves to the right side
        more = lp_objective(prog, prog.b_eq - eps * prog.exchange_eq[b], prog.b_ub - eps * prog.exchange_ub[:, b])
        assert (more - base) / eps == pytest.approx(r.bus_price[h, b], rel=1e-5, abs=1e-5), net.buses[b]


# --- curtailment ------------------------------------------------------------------------------------------------

def generating(s_max: float, generation: float):
    """0-1-2, bus 2 producing ``generation`` MW of fixed generation (a negative fixed load) behind line 1-2."""
    buses = [{"name": "0"}, {"name": "1", "p_mw": 0.5}, {"name": "2", "p_mw": -generation}]
    lines = [{"from": "0", "to": "1", "r_ohm": 0.01, "x_ohm": 0.01, "s_max_mva": 100.0},
             {"from": "1", "to": "2", "r_ohm": 0.01, "x_ohm": 0.01, "s_max_mva": s_max}]
    return build("gen3", 10.0, buses, lines, "0", v_min=0.5, v_max=1.5, load_profile=(1.0,) * HOURS)


@pytest.mark.parametrize("method", ["lindistflow", "ac"])
def test_generation_no_line_can_carry_is_spilled_at_the_spill_price_and_reported(method):
    net = generating(3.0, 5.0)
    r = clear_network([], net, {}, 40.0, WIDE, WIDE, method=method)  # raised before: nothing but generation to shed
    assert r.spill_mw[0, 2] == pytest.approx(2.0, abs=1e-3) and not r.shed_mw.any()
    assert r.flow_p[0, 1] == pytest.approx(-3.0, abs=1e-3)  # line 1-2 carries what it can, back to the substation
    assert r.bus_price[0, 2] == pytest.approx(0.0, abs=1e-6)  # a MW more load there would save a MW of spill
    priced = clear_network([], net, {}, 40.0, WIDE, WIDE, method=method, spill_price=12.5)
    assert priced.bus_price[0, 2] == pytest.approx(-12.5, abs=1e-6)
    assert priced.welfare[0] == pytest.approx(r.welfare[0] - 12.5 * float(r.spill_mw[0, 2]), abs=1e-6)
    # a buyer behind the line takes some of the surplus at its bus's price: less is spilled
    buyer = clear_network([one_hour("mg", [(30.0, 1.0)])], net, {"mg": "2"}, 40.0, WIDE, WIDE, method=method)
    assert at(buyer)["mg"] == pytest.approx(1.0) and buyer.spill_mw[0, 2] == pytest.approx(1.0, abs=1e-3)
    prog = hour_program([], net, {}, 0, 40.0, WIDE, WIDE, method=method, spill_price=12.5)
    kkt(prog)


def test_a_spill_price_outside_zero_to_voll_is_refused_in_one_line():
    for price in (-1.0, VOLL * 2, math.nan):
        with pytest.raises(ValueError, match="spill_price") as e:
            clear_network([], generating(3.0, 5.0), {}, 40.0, WIDE, WIDE, spill_price=price)
        assert "\n" not in str(e.value)


def test_a_reactive_load_no_clearing_can_shed_whose_line_is_full_in_ac_is_cleared_and_its_overload_reported():
    # 0.5 Mvar and no P at bus 1, its line rated by the rule at exactly 0.5 MVA: full on LinDistFlow, 3.4% over in AC
    # (the line's own reactive losses), and a load with no P cannot be shed; found by tests/dmosim/test_feeder_check.py
    net = build("q", 4.0, [{"name": "0"}, {"name": "1", "q_mvar": 0.5}],
                [{"from": "0", "to": "1", "r_ohm": 1.0, "x_ohm": 1.0}], "0", rating_margin=1.0,
                load_profile=(1.0,) * HOURS)
    r = clear_network([], net, {}, 40.0, WIDE, WIDE, method="ac")
    assert all(0.03 < x < 0.04 for x in r.ac_overload) and not r.shed_mw.any()


def lossy_pair(load_mw: float = 1.0):
    """0-1, a line of 0.01 p.u. (1 ohm at 10 kV) to a bus with ``load_mw`` of load: a MW more there costs 2% more
    losses at 1 MW of flow, 2% less at -1 MW."""
    buses = [{"name": "0", "p_mw": 0.0, "q_mvar": 0.0}, {"name": "1", "p_mw": load_mw, "q_mvar": 0.0}]
    lines = [{"from": "0", "to": "1", "r_ohm": 1.0, "x_ohm": 1.0, "s_max_mva": 1e4}]
    return build("pair", 10.0, buses, lines, "0", v_min=0.5, v_max=1.5, load_profile=(1.0,) * HOURS)


def marginal_price(net, energy: float, award_mw: float, h: float = 1e-5) -> float:
    """What a MW more at bus 1 costs at the substation's ``energy`` price, by central differences of the AC
    losses (the branch-flow equations, checked against pandapower in test_acflow) at the plan itself."""
    from dmo.market.branchflow import BranchFlow

    flow = BranchFlow(net)

    def losses(dp: float) -> float:
        p = net.fixed_p[0].copy()
        p[1] += award_mw + dp
        return flow.solve(p, net.fixed_q[0]).losses

    return energy * (1.0 + (losses(h) - losses(-h)) / (2 * h))


def test_a_seller_whose_own_losses_move_its_price_across_its_bid_is_settled_where_they_meet_it():
    # 4 MW offered at $40.40 with energy at $40 behind a lossy line to 1 MW of load: with none sold, a MW more there
    # saves 2% of losses (its price $40.80, in the money); with all 4 MW sold, the line carries 3 MW out and a MW
    # more costs 6% of losses (price $37.60, out of it). The clearings linearised at each plan alternate between
    # all and nothing; the hour is settled at the plan between them whose own marginal losses price it at its bid.
    net = lossy_pair()
    r = clear_network([one_hour("s", [(40.4, -4.0)])], net, {"s": "1"}, 40.0, WIDE, WIDE, method="ac")
    sold = r.awards["s"][0]
    assert -4.0 + 0.1 < sold < -0.1
    assert r.agent_price["s"][0] == 40.4 and r.energy[0] == 40.0
    assert marginal_price(net, 40.0, sold) == pytest.approx(40.4, abs=1e-3)  # the plan's own AC flow prices it so
    parts = r.energy[:, None] + r.loss + r.congestion + r.voltage
    assert (np.abs(parts - r.bus_price) <= 1e-9 * np.abs(r.bus_price)).all()
    assert 1 <= r.iterations[0] < 20 and r.ac_voltage_excess_pu[0] == 0.0


def test_equal_sellers_settled_at_one_bus_share_alike_whatever_their_order():
    net = lossy_pair()
    alone = clear_network([one_hour("s", [(40.4, -4.0)])], net, {"s": "1"}, 40.0, WIDE, WIDE, method="ac")
    bids = [one_hour("s", [(40.4, -2.0)]), one_hour("t", [(40.4, -2.0)])]
    pair = clear_network(bids, net, {"s": "1", "t": "1"}, 40.0, WIDE, WIDE, method="ac")
    swapped = clear_network(bids[::-1], net, {"s": "1", "t": "1"}, 40.0, WIDE, WIDE, method="ac")
    assert at(pair)["s"] == at(pair)["t"] == at(swapped)["s"] == at(swapped)["t"] < -0.1
    assert at(pair)["s"] + at(pair)["t"] == pytest.approx(at(alone)["s"], abs=1e-6)


def test_where_the_shares_lp_fails_the_lps_own_plan_stands_and_keeps_every_limit():
    # Found by the permutation property: $10 buyers at buses 1 and 4 set the price with the import limit full; the
    # line to bus 4 binds with no dual, and the LP of the shares is infeasible. Sharing the LP's plan out pro rata
    # per class, as before, put 3.26 MW behind that 3 MW line.
    bids = [one_hour("mg2", [(0.0, 1.0)], 20), one_hour("mg3", [(0.0, 1.0), (10.0, 4.0)], 20),
            one_hour("mg4", [(0.0, 1.0), (10.0, 2.0), (0.0, 1.0)], 20)]
    where = {"mg2": "2", "mg3": "4", "mg4": "1"}
    r = clear_network(bids, TIGHT, where, 0.0, 6.0, 0.0)
    network_limits_hold(TIGHT, r)
    awards_follow_prices(bids, r)
    assert r.congested[20] == "import" and r.price[20] == 10.0
