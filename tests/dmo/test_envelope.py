"""Operating envelopes (docs/network.md, "Operating envelopes"): every corner of the microgrids' boxes keeps the feeder
within its limits, the rooms each way are max-min fair, a binding limit leaves the buses behind it no room towards it
and room away from it, and a feeder no limit of which binds shares the substation's room each way."""

from __future__ import annotations

import numpy as np
import pytest

from dmo.market.clearing import BidCurve, Step
from dmo.market.distflow import FACETS, Feeder, clear_network
from dmo.market.envelope import operating_envelope
from dmosim.bench.clearing import market_day
from dmo.operator import feeder as dmo_feeder
from dmo.operator import outbox
from dmo.operator.config import DayConfig
from messages import decode, encode
from scenarios.horizon import HOURS
from scenarios.network import load_network
from test_distflow import chain, one_hour

TOL = 1e-9
MARGIN = 0.005


def random_day(network, agents: int, block: float, seed: int):
    """Agents at random buses (several at a bus), each hour buying one or two blocks and selling one, the sales up
    to three blocks so that flows run back to the substation in some hours; substation limits that bind sometimes."""
    rng = np.random.default_rng(seed)
    feeder = [b for b in network.buses if b != network.substation]
    buses = {f"mg{i:02d}": feeder[int(rng.integers(len(feeder)))] for i in range(agents)}
    bids = []
    for a in buses:
        hours = []
        for _ in range(HOURS):
            buys = [Step(float(rng.uniform(30, 120)), float(block * rng.uniform(0.1, 1.5)))
                    for _ in range(int(rng.integers(1, 3)))]
            sell = Step(float(rng.uniform(0, 70)), -float(block * rng.uniform(0.1, 3.0)))
            hours.append(tuple(buys + [sell]))
        bids.append(BidCurve(a, tuple(hours)))
    iso = rng.uniform(20, 80, HOURS).round(2).tolist()
    load = float(network.load_p_mw.sum())
    imp, exp = 1.5 * load + agents * block * 0.6, load + agents * block * 0.6
    return clear_network(bids, network, buses, iso, imp, exp, margin=MARGIN), buses, imp, exp


@pytest.fixture(scope="module", params=[("feeder5", 1.0, 6, 1.2), ("feeder5", 0.9, 9, 0.8), ("ieee33", 0.95, 40, 0.12)],
                ids=["feeder5", "feeder5-pf0.9", "ieee33"])
def day(request):
    name, pf, agents, block = request.param
    network = load_network(name, power_factor=pf)
    clearing, buses, imp, exp = random_day(network, agents, block, seed=len(name) + agents)
    return network, clearing, buses, imp, exp, operating_envelope(clearing, network, buses, imp, exp, MARGIN)


def limits_excess(network, imp, exp, p, q):
    """Per load vector (rows of p and q, MW and Mvar per bus), every limit's excess over its bound, computed from
    ``Network.lindistflow`` alone: 8 facets per line, each bus's lower and upper voltage (U = V^2, within the
    margin), the substation's import and export."""
    flow_p, flow_q, v = network.lindistflow(p, q)
    facets = FACETS[:, :1, None] * flow_p.T[None] + FACETS[:, 1:, None] * flow_q.T[None] - network.s_max_mva[None, :,
                                                                                                               None]
    u = v ** 2
    feeder = np.arange(network.n_buses) != network.root
    low = ((network.v_min + MARGIN) ** 2 - u)[:, feeder]
    high = (u - (network.v_max - MARGIN) ** 2)[:, feeder]
    p0 = p.sum(axis=1)
    return np.concatenate([facets.reshape(-1, len(p)).T, low, high, (p0 - imp)[:, None], (-exp - p0)[:, None]],
                          axis=1)


def test_every_corner_of_the_boxes_keeps_every_limit_the_plan_keeps(day):
    """All up, all down and 300 random corners per hour: each microgrid at its award plus its bus's import room or
    less its export room. No limit ends more than 1e-9 beyond where the plan left it (or beyond its bound, if the
    plan kept it)."""
    network, clearing, buses, imp, exp, rooms = day
    rng = np.random.default_rng(7)
    names = sorted(clearing.awards)
    at = np.array([network.index[buses[a]] for a in names])
    onto = np.zeros((len(names), network.n_buses))
    onto[np.arange(len(names)), at] = 1.0
    tan = network.tan_phi
    for h in range(HOURS):
        award = np.array([clearing.awards[a][h] for a in names])
        signs = np.vstack([np.ones(len(names)), -np.ones(len(names)), rng.choice([-1.0, 1.0], (300, len(names)))])
        p_m = award + np.where(signs > 0, rooms.import_mw[h, at], -rooms.export_mw[h, at])
        plan_p = network.fixed_p[h] + award @ onto
        p = network.fixed_p[h] + p_m @ onto
        q = network.fixed_q[h] + tan * (p_m @ onto)
        planned = limits_excess(network, imp, exp, plan_p[None], (network.fixed_q[h] + tan * (award @ onto))[None])
        excess = limits_excess(network, imp, exp, p, q)
        assert (excess <= np.maximum(planned, 0.0) + TOL).all(), (h, excess.max())
    for room in (rooms.import_mw, rooms.export_mw):
        assert room.min() >= 0 and np.isfinite(room).all() and not room.flags.writeable
        assert (room[:, at] > 0).any() and (room[:, at] == 0).any()  # the day has hours with room and hours without
        assert (room[:, np.setdiff1d(np.arange(network.n_buses), at)] == 0).all()  # no microgrid, no room


def dense_limits(network, clearing, buses, imp, exp, h):
    """Hour h's limits written out whole from ``Feeder.limits``: g per limit and bus (the substation's import row
    of ones and export row of minus ones last), each limit's slack at the plan (clamped at 0) and the number of
    microgrids per bus."""
    feeder = Feeder(network, MARGIN)
    g_p, g_q, b = feeder.limits(feeder.rows)
    ones = np.ones((1, network.n_buses))
    g = np.vstack([g_p + network.tan_phi * g_q, ones, -ones])
    count = np.zeros(network.n_buses)
    inject = np.zeros(network.n_buses)
    for a, bus in buses.items():
        count[network.index[bus]] += 1
        inject[network.index[bus]] += clearing.awards[a][h]
    p, q = network.fixed_p[h] + inject, network.fixed_q[h] + network.tan_phi * inject
    p0 = p.sum()
    slack = np.concatenate([b - (g_p @ p + g_q @ q), [imp - p0, p0 + exp]])
    return g, np.maximum(slack, 0.0), count


def test_the_rooms_each_way_are_max_min_fair(day):
    """Each way, every bus with a microgrid has a bottleneck: a limit its room moves towards its bound, held at its
    slack by the rooms, in which no bus it moves has more room. Then no bus's room can grow without shrinking a room
    no larger (max-min fairness), and the robust sums hold for every limit: sum_j max(g_ij u_j, -g_ij e_j) <= s_i
    with every microgrid at the worse end of its range."""
    network, clearing, buses, imp, exp, rooms = day
    for h in range(HOURS):
        g, slack, count = dense_limits(network, clearing, buses, imp, exp, h)
        worst = np.maximum(g * (count * rooms.import_mw[h]), -g * (count * rooms.export_mw[h])).sum(axis=1)
        assert (worst <= slack + TOL * np.maximum(1.0, slack)).all(), h
        for room, towards in ((rooms.import_mw[h], np.maximum(g, 0.0)), (rooms.export_mw[h], np.maximum(-g, 0.0))):
            used = towards @ (count * room)
            tight = used >= slack - TOL * np.maximum(1.0, slack)
            for j in np.flatnonzero(count):
                moved = tight & (towards[:, j] > 0)
                members = (towards[moved] > 0) & (count > 0)
                top = np.where(members, room[None, :], -np.inf).max(axis=1)
                assert (room[j] >= top - TOL).any(), (h, network.buses[j])


def test_buses_behind_a_binding_line_get_no_room_towards_it_and_room_away_from_it():
    # feeder5's line 2-3 (3 MVA): the buyer at bus 3 congests it in hour 1; the agents at buses 1 and 4 keep room
    network = load_network("feeder5")
    bids = [one_hour("far", [(90, 5)]), one_hour("near", [(60, 0.5)]), one_hour("side", [(60, 0.5)])]
    buses = {"far": "3", "near": "1", "side": "4"}
    clearing = clear_network(bids, network, buses, 40, 100, 100)
    assert clearing.congested[0] == "line"
    rooms = operating_envelope(clearing, network, buses, 100, 100)
    far, near, side = (network.index[b] for b in ("3", "1", "4"))
    assert rooms.import_mw[0, far] == 0 and rooms.export_mw[0, far] > 1.0  # importing less relieves the line
    assert (rooms.import_mw[0, [near, side]] > 0.1).all() and (rooms.export_mw[0, [near, side]] > 0.1).all()
    # an hour with no award anywhere leaves the line's room to the far bus too
    assert rooms.import_mw[1, far] > 0


def test_a_feeder_whose_limits_never_bind_shares_the_substations_room():
    network = chain(5, load=0.3)
    buses = {"a": "1", "b": "4", "c": "4"}
    bids = [one_hour("a", [(50, 1.0)]), one_hour("b", [(50, -0.5)]), one_hour("c", [(50, 2.0)])]
    imp, exp = 5.0, 3.0
    clearing = clear_network(bids, network, buses, 40, imp, exp)
    rooms = operating_envelope(clearing, network, buses, imp, exp)
    for h in range(HOURS):
        p0 = network.fixed_p[h].sum() + clearing.net_import(h)
        for room, share in ((rooms.import_mw, (imp - p0) / 3), (rooms.export_mw, (p0 + exp) / 3)):
            assert room[h, [1, 4]] == pytest.approx([share, share], rel=1e-12)  # three microgrids, the same room
            assert (room[h, [0, 2, 3]] == 0).all()
    assert rooms.import_mw[0, 1] == pytest.approx((5.0 - 1.2 - 1.0 - 2.0) / 3, rel=1e-12)  # b sells nothing at $40
    assert rooms.export_mw[0, 1] == pytest.approx((3.0 + 1.2 + 1.0 + 2.0) / 3, rel=1e-12)


def test_left_sides_are_the_limits_rows_and_each_row_has_one_sign():
    """What the envelope relies on: ``Feeder.left_sides`` is ``limits``' G_P p + G_Q q for every row, ``bounds``
    its b, and a microgrid's g = G_P + tan(phi) G_Q has one sign along each row, so |G x| is |G| x for x >= 0."""
    network = load_network("ieee33", power_factor=0.9)
    feeder = Feeder(network, MARGIN)
    g_p, g_q, b = feeder.limits(feeder.rows)
    rng = np.random.default_rng(1)
    p, q = rng.normal(size=network.n_buses), rng.normal(size=network.n_buses)
    np.testing.assert_allclose(feeder.left_sides(p, q), g_p @ p + g_q @ q, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(feeder.bounds, b)
    g = g_p + network.tan_phi * g_q
    assert ((g >= 0).all(axis=1) | (g <= 0).all(axis=1)).all()
    for _ in range(20):  # ``behind`` is the nonzero pattern of g over any set of limits
        rows = np.sort(rng.choice(feeder.rows, int(rng.integers(1, 6)), replace=False))
        at = np.searchsorted(feeder.rows, rows)
        np.testing.assert_array_equal(feeder.behind(rows), (g[at] != 0).any(axis=0))


def test_bad_inputs_are_refused_in_one_line():
    network = load_network("feeder5")
    bids = [one_hour("a", [(50, 1.0)])]
    clearing = clear_network(bids, network, {"a": "1"}, 40, 10, 10)
    with pytest.raises(ValueError, match="agent a has no bus"):
        operating_envelope(clearing, network, {}, 10, 10)
    with pytest.raises(ValueError, match="substation"):
        operating_envelope(clearing, network, {"a": "0"}, 10, 10)
    with pytest.raises(ValueError, match="import_limit"):
        operating_envelope(clearing, network, {"a": "1"}, -1, 10)


def test_the_dmos_grid_states_carry_each_hours_rooms_at_every_bus_and_none_on_the_copper_plate():
    network = load_network("feeder5")
    settings = dict(market_day="2026-07-01", agents=2, iso_price=(40.0,) * HOURS, import_limit=100.0,
                    export_limit=100.0, penalty=150.0, subperiods=2, islanded_hours=(5,), credit=0.0,
                    registration_s=1.0, bids_s=1.0, schedule_s=1.0, hour_s=1.0)
    buses = {"far": "3", "near": "1"}
    clearing = clear_network([one_hour("far", [(90, 5)]), one_hour("near", [(60, 0.5)])], network, buses, 40, 100,
                             100)
    config = DayConfig(**settings, network=network, placement=buses, voltage_margin=0.01)
    rooms = dmo_feeder.envelope(config, clearing, buses)
    again = operating_envelope(clearing, network, buses, 100.0, 100.0, 0.01)
    np.testing.assert_array_equal(rooms.import_mw, again.import_mw)
    np.testing.assert_array_equal(rooms.export_mw, again.export_mw)
    for hour in (1, 2, 5):
        grid = decode(encode(outbox.grid_state(config, 1, hour, rooms)))
        assert grid.buses == network.buses and grid.import_room_mw == tuple(rooms.import_mw[hour - 1])
        assert grid.export_room_mw == tuple(rooms.export_mw[hour - 1])
        assert grid.connected == ((False,) * 2 if hour == 5 else (True,) * 2)  # islanded: the rooms come anyway
    assert grid.import_room_mw[network.index["1"]] > 0 and grid.import_room_mw[network.index["2"]] == 0  # none at 2
    plate = outbox.grid_state(DayConfig(**settings), 1, 1)
    assert (plate.buses, plate.import_room_mw, plate.export_room_mw) == ((), (), ())


@pytest.mark.parametrize("method", ["lindistflow", "ac"])
def test_on_ieee33_a_binding_voltage_leaves_room_only_in_the_direction_that_relieves_it(method):
    """``dmosim bench clearing``'s day of 30 agents holds a bus at its lower voltage limit in most hours. There the
    buses that move it get no import room (importing more lowers it) and every microgrid keeps export room."""
    network = load_network("ieee33")
    bids, buses, iso, limit = market_day(network, 30, 0)
    clearing = clear_network(bids, network, buses, iso, limit, limit, method=method)
    rooms = operating_envelope(clearing, network, buses, limit, limit)
    at = np.array([network.index[b] for b in buses.values()])
    feeder = Feeder(network)
    hours = [h for h in range(HOURS) if clearing.buses_binding[h]]
    assert len(hours) >= 12
    for h in hours:
        low = np.array(clearing.buses_binding[h])
        assert np.allclose(clearing.voltage_pu[h, low], network.v_min[low], atol=1e-6)  # at the lower limit
        behind = feeder.behind(8 * network.n_lines + 2 * low)
        assert behind[at].any() and (rooms.import_mw[h, behind] <= TOL).all(), h
        assert (rooms.export_mw[h, at] > 1e-3).all(), h
