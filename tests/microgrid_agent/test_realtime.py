"""Rolling-horizon real-time operation: the realised day is a valid schedule, islanding is obeyed, hours run in order."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dmo.market.rules import BUILT_IN
from dmo.market.settlement import settle
from microgrid_agent.agent.realtime import Operator, Room
from microgrid_agent.checker import check_schedule
from microgrid_agent.model import DeviationCost, Params, first_stage_of
from microgrid_agent.solvers.extensive import SolveError, solve
from microgrid_agent.solvers.rolling import RollingLP
from scenarios.case import load_case
from scenarios.days import carry_over, day_seed
from scenarios.generation import ScenarioSet, make_scenarios, sample

K = 1
PENALTY = 150.0


@pytest.fixture(scope="module")
def case():
    return load_case("paper")


@pytest.fixture(scope="module")
def p_sch(case):
    return np.asarray(case.grid.p_sch, float)


@pytest.fixture(scope="module")
def first_stage(case, p_sch):
    """A day-ahead schedule at hourly resolution on two scenarios, verified."""
    scen = make_scenarios(case, 2, K, island_hours=1, seed=0)
    schedule = solve(case, scen, Params(p_sch, PENALTY), gap=1e-3)
    check_schedule(case, scen, schedule, p_sch=p_sch, penalty=PENALTY).raise_if_failed()
    return first_stage_of(schedule)


def operator(case, first_stage, p_sch, seed, subperiods=K):
    realised = sample(case, 1, subperiods, island_hours=0, seed=seed)
    return Operator(case, first_stage, p_sch, PENALTY, subperiods, realised)


def operate(op, hour, connected, case, p_sch):
    """One hour, with the rolling LP's whole-day plan verified by the checker."""
    result = op.operate_hour(hour, connected)
    check_schedule(case, result.plan_scenario, result.plan, p_sch=p_sch, penalty=PENALTY).raise_if_failed()
    return result


@pytest.fixture(scope="module")
def day(case, first_stage, p_sch):
    op = operator(case, first_stage, p_sch, seed=11)
    hours = [operate(op, h, [True] * K, case, p_sch) for h in range(1, 25)]
    return op, hours, op.day_result()


def test_realised_day_is_a_valid_schedule(case, p_sch, day):
    _, _, result = day
    report = check_schedule(case, result.scenario, result.schedule, p_sch=p_sch, penalty=PENALTY)
    report.raise_if_failed()
    assert report.objective == pytest.approx(result.cost.total)


def test_realised_day_keeps_the_commitment_and_the_physics(case, first_stage, day):
    _, hours, result = day
    d, scen = result.schedule.dispatch, result.scenario
    on = np.repeat(first_stage["I"], K, axis=1)
    assert np.all(d.p_unit[:, 0][on == 0] == 0)
    supply = d.p_unit.sum(axis=0) + d.p_renewable.sum(axis=0) + d.p_storage + d.p_m + d.load_shed
    np.testing.assert_allclose(supply, scen.load + d.d_load.sum(axis=0), atol=1e-6)
    assert np.all(d.soc >= -1e-7) and np.all(d.soc <= case.storage.c_max + 1e-7)
    assert d.soc[0, -1] >= case.storage.c_initial - 1e-6
    np.testing.assert_allclose(d.d_load[:, 0].sum(axis=1) / K, case.load_array("energy"), rtol=1e-6)
    # the hour results are the day's arrays, and the hour costs add up to the day's
    np.testing.assert_allclose(np.concatenate([h.p_m for h in hours]), result.p_m)
    np.testing.assert_allclose([h.soc_end for h in hours], d.soc[0, K - 1::K])
    assert math.fsum(h.cost.total for h in hours) == pytest.approx(result.cost.total)


@pytest.mark.slow
@pytest.mark.parametrize("rule, params", [("paper", {"penalty": PENALTY}),
                                          ("deadband", {"rate": PENALTY, "below_rate": 40.0, "band_mw": 0.5})])
def test_the_operators_penalty_is_what_the_dmo_bills_for_its_reports(case, first_stage, rule, params):
    """Against an award that the realised day both exceeds and undershoots, each hour's penalty in the agent's own
    cost is what the DMO's settlement charges, penalty less credit, for the meter readings the agent reports (to
    the cent), under the paper's rule and under another rule the agent operates against; and the reported
    deviations are what the DMO reads off those readings."""
    p_sch = np.where(np.arange(24) % 2, 0.0, 12.0)  # nothing on odd hours, more than needed on even ones
    pieces = BUILT_IN[rule].deviation_cost(params, p_sch, [0.0] * 24)
    cost = None if rule == "paper" else DeviationCost.from_pieces(pieces)
    op = Operator(case, first_stage, p_sch, PENALTY, K, sample(case, 1, K, island_hours=0, seed=5),
                  deviation_cost=cost)
    hours = [op.operate_hour(h, [True] * K) for h in range(1, 25)]
    meter = {"mg1": {h.hour - 1: tuple(float(x) for x in h.p_m) for h in hours}}
    statements, _ = settle({"mg1": p_sch}, [0.0] * 24, meter, subperiods=K, p_m_max=case.grid.p_m_max,
                           rule=BUILT_IN[rule], **params)
    billed = [float(line.penalty - line.credit) for line in statements["mg1"].lines]
    assert billed == pytest.approx([h.cost.penalty for h in hours], abs=0.005)
    assert any(b > 0 for b in billed) and any(b == 0 for b in billed)
    for h, line in zip(hours, statements["mg1"].lines):
        assert line.deviation_mwh == pytest.approx(np.maximum(h.deviation, 0).sum() / K, abs=1e-9)
        assert line.under_import_mwh == pytest.approx(np.maximum(-h.deviation, 0).sum() / K, abs=1e-9)
    result = op.day_result()
    check_schedule(case, result.scenario, result.schedule, p_sch=p_sch, penalty=PENALTY,
                   deviation_cost=result.deviation_cost).raise_if_failed()


def test_islanded_subperiods_have_no_grid_transfer(case, first_stage, p_sch):
    op = operator(case, first_stage, p_sch, seed=3, subperiods=2)
    operate(op, 1, [True, True], case, p_sch)
    islanded = operate(op, 2, [False, False], case, p_sch)
    partly = operate(op, 3, [True, False], case, p_sch)
    assert np.all(islanded.p_m == 0) and not islanded.connected.any()
    assert partly.p_m[1] == 0 and partly.connected.tolist() == [True, False]
    assert not islanded.surplus.any() and not partly.surplus.any()  # the load takes what the units make
    assert np.all(islanded.deviation == -p_sch[1])
    # the plan's future is grid-connected on the forecast: only the announced sub-periods are islanded
    assert partly.plan_scenario.connected[0].tolist() == [1, 1, 0, 0, 1, 0] + [1] * 42


def test_islanded_generation_the_load_cannot_take_is_let_out_and_the_day_goes_on(case, first_stage, p_sch):
    """Islanded, with a load far below the committed units' minimum outputs: the surplus is let out (and only
    there), the balance (2) holds with it, the next hour is operated as usual, and the realised day carries it."""
    realised = sample(case, 1, K, island_hours=0, seed=3)
    light = ScenarioSet(K, realised.probability, realised.load * 0.01, realised.renewable, realised.connected)
    op = Operator(case, first_stage, p_sch, PENALTY, K, light)
    assert op.first.commitment[:, 0].any()
    islanded = op.operate_hour(1, [False] * K)
    assert (islanded.surplus > 0.1).all() and (islanded.p_m == 0).all()
    supply = islanded.p_unit.sum(0) + islanded.p_renewable.sum(0) + islanded.p_storage + islanded.load_shed
    np.testing.assert_allclose(supply - islanded.surplus, light.load[0, :K] + islanded.d_load.sum(0), atol=1e-6)
    for hour in range(2, 25):
        assert not op.operate_hour(hour, [True] * K).surplus.any()
    np.testing.assert_array_equal(op.day_result().surplus, np.concatenate([islanded.surplus, np.zeros(23 * K)]))


def test_an_hour_that_cannot_be_operated_is_named_with_its_connection(case, first_stage, p_sch):
    op = Operator(case, first_stage, p_sch, PENALTY, K, sample(case, 1, K, island_hours=0, seed=3), time_limit=1e-9)
    with pytest.raises(SolveError, match=r'^hour 1 \(islanded\) cannot be operated: the real-time LP is .*'
                                         r'\(docs/agent\.md, "Feasibility"\)$'):
        op.operate_hour(1, [False] * K)


def test_hours_must_come_in_order(case, first_stage, p_sch):
    op = operator(case, first_stage, p_sch, seed=1)
    with pytest.raises(ValueError, match="expected hour 1"):
        op.operate_hour(2, [True])
    with pytest.raises(ValueError, match="booleans"):
        op.operate_hour(1, [True, True])
    with pytest.raises(ValueError, match="not over"):
        op.day_result()
    operate(op, 1, [True], case, p_sch)
    with pytest.raises(ValueError, match="expected hour 2"):
        op.operate_hour(1, [True])
    assert op.next_hour == 2


def test_day_over_refuses_more_hours(day):
    op, _, _ = day
    with pytest.raises(ValueError, match="day is over"):
        op.operate_hour(25, [True])


def test_operator_is_deterministic_for_a_seed(case, first_stage, p_sch):
    runs = []
    for seed in (5, 5, 6):
        op = operator(case, first_stage, p_sch, seed=seed)
        runs.append([operate(op, h, [True], case, p_sch) for h in (1, 2)])
    for a, b in zip(runs[0], runs[1]):
        for field in ("p_m", "p_unit", "p_storage", "soc", "d_load", "load_shed"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(runs[0][0].plan_scenario.load, runs[2][0].plan_scenario.load)


def test_bad_inputs_are_refused(case, first_stage, p_sch):
    two = sample(case, 2, K, island_hours=0, seed=0)
    with pytest.raises(ValueError, match="one scenario"):
        Operator(case, first_stage, p_sch, PENALTY, K, two)
    with pytest.raises(ValueError, match="penalty"):
        Operator(case, first_stage, p_sch, -1.0, K, two.single(0))


def test_the_next_day_starts_where_the_operated_day_ended(case, p_sch, day):
    """Day 2's schedule starts from day 1's midnight: the stored energy, each unit's state, output and hours in
    that state; the checker holds it to its ramps from that output and to the minimum times still owed."""
    op, _, result = day
    midnight = op.midnight()
    d = result.schedule.dispatch
    assert midnight.stored_mwh == pytest.approx(d.soc[0, -1])
    assert list(midnight.unit_on) == [bool(x) for x in result.schedule.first.commitment[:, -1]]
    np.testing.assert_allclose(midnight.unit_output_mw, d.p_unit[:, 0, -1])
    tomorrow = carry_over(case, midnight, name="paper-day2")
    scen = make_scenarios(tomorrow, 2, K, island_hours=1, seed=day_seed(0, 2))
    schedule = solve(tomorrow, scen, Params(p_sch, PENALTY), gap=1e-3)
    check_schedule(tomorrow, scen, schedule, p_sch=p_sch, penalty=PENALTY).raise_if_failed()
    first_hour = schedule.first.commitment[:, 0]
    for unit, on in zip(tomorrow.units, first_hour):
        if unit.keep_initial_hours:
            assert on == unit.initial_on
    # the day may not borrow from the next: it ends with at least the energy it started with
    assert schedule.dispatch.soc[:, -1].min() >= tomorrow.storage.c_initial - 1e-6
    with pytest.raises(ValueError, match="not over"):
        operator(case, first_stage_of(schedule), p_sch, seed=3).midnight()


# --- the operating envelope of a feeder (docs/network.md, "Operating envelopes") ---------------------------------

SWING = np.where(np.arange(24) % 2, 0.0, 12.0)  # nothing on odd hours, more than the microgrid can take on even ones


def swinging(case, first_stage, subperiods=K):
    """An operator whose award it cannot follow: each hour's P_M strays from it."""
    return Operator(case, first_stage, SWING, PENALTY, subperiods, sample(case, 1, subperiods, island_hours=0, seed=5))


def test_a_small_room_holds_p_m_within_it_of_the_award_on_its_own_side(case, first_stage):
    free, held, below = (swinging(case, first_stage, 2) for _ in range(3))
    for op in (free, held, below):
        for h in range(1, 8):
            op.operate_hour(h, [True, True])
    wanted = free.operate_hour(8, [True, False])
    got = held.operate_hour(8, [True, False], room=Room(import_mw=0.5, export_mw=3.0))
    assert wanted.p_m[0] - SWING[7] > 1.0  # without the envelope the hour imports well above its award of 0
    assert got.p_m[0] == pytest.approx(SWING[7] + 0.5, abs=1e-9)  # held at the import room's edge
    assert got.p_m[1] == 0 and not got.connected[1]  # islanded: 0 whatever the room
    assert got.room == Room(0.5, 3.0) and not got.envelope_infeasible and wanted.room is None
    # an export room alone does not hold an hour that wants to import more
    np.testing.assert_array_equal(below.operate_hour(8, [True, False], room=Room(import_mw=40.0, export_mw=0.0)).p_m,
                                  wanted.p_m)
    result = held.operate_hour(9, [True, True])  # the next hour, without an envelope, goes on from there
    check_schedule(case, result.plan_scenario, result.plan, p_sch=SWING, penalty=PENALTY).raise_if_failed()


def test_a_room_wider_than_the_microgrids_limits_changes_nothing_and_a_room_that_does_not_bind_costs_nothing(
        case, first_stage):
    ops = [swinging(case, first_stage) for _ in range(3)]
    for op in ops:
        op.operate_hour(1, [True])
    free, wide, loose = (op.operate_hour(2, [True], room) for op, room in zip(ops, (None, Room(40.0, 40.0),
                                                                                       Room(1.0, 1.0))))
    for field in ("p_m", "p_unit", "p_renewable", "p_storage", "soc", "d_load", "load_shed"):
        np.testing.assert_array_equal(getattr(wide, field), getattr(free, field))
    assert wide.room == Room(40.0, 40.0) and not wide.envelope_infeasible
    assert abs(loose.p_m[0] - SWING[1]) < 1.0  # within the room: it did not bind
    assert loose.cost.total == pytest.approx(free.cost.total, rel=1e-9)


def test_an_hour_that_cannot_keep_its_envelope_is_operated_without_it(case, first_stage):
    free, held = swinging(case, first_stage), swinging(case, first_stage)
    wanted = free.operate_hour(1, [True])
    assert SWING[0] - wanted.p_m[0] > 1.0  # 12 MW is more than the committed microgrid can take in hour 1
    got = held.operate_hour(1, [True], room=Room(0.5, 0.5))
    assert got.envelope_infeasible and got.room is None
    np.testing.assert_array_equal(got.p_m, wanted.p_m)
    with pytest.raises(ValueError, match="room"):
        held.operate_hour(2, [True], room=0.5)
    for bad in (-0.1, math.inf, math.nan, True, "1"):
        with pytest.raises(ValueError, match="room's import_mw must be a finite number of MW >= 0"):
            Room(bad, 0.0)


# --- the rolling LP, compiled once (solvers/rolling.py) ------------------------------------------------------------

DISPATCH = ("p_unit", "p_renewable", "p_storage", "soc", "d_load", "p_m", "load_shed", "dp_plus")
PINNED = {"P": "p_unit", "Pr": "p_renewable", "Pst": "p_storage", "C": "soc", "D": "d_load", "PM": "p_m",
          "LS": "load_shed"}


def test_each_hours_lp_is_the_extensive_form_and_depends_on_that_hours_data_alone(case, first_stage):
    """Hour by hour (islanded sub-periods and an envelope among them), the rolling LP's plan costs what cvxpy's
    extensive form costs with the same first stage, past and envelope; a fresh LP given the same hour plans the
    same, bit for bit (an agent restarted mid-day operates as one that was not); and an LP whose compiled matrix
    no longer matches takes the model anew and plans the same too."""
    k, n = 2, 24 * 2
    op = swinging(case, first_stage, k)
    params = Params(SWING, PENALTY)
    done = {"P": np.zeros((len(case.units), n)), "Pr": np.zeros((len(case.renewables), n)),
            "Pst": np.zeros((1, n)), "C": np.zeros((1, n)), "D": np.zeros((len(case.loads), n)),
            "PM": np.zeros((1, n)), "LS": np.zeros((1, n))}
    connection = {3: [False, False], 4: [True, False]}
    for hour in range(1, 7):
        n0, n1 = (hour - 1) * k, hour * k
        room = Room(0.5, 0.25) if hour in (5, 6) else None
        result = op.operate_hour(hour, connection.get(hour, [True] * k), room)
        bounds = None
        if result.room is not None:
            limit = case.grid.p_m_max
            bounds = (n0, np.full(k, max(SWING[hour - 1] - room.export_mw, -limit)),
                      np.full(k, min(SWING[hour - 1] + room.import_mw, limit)))
        past = {name: value.copy() for name, value in done.items()}
        reference = solve(case, result.plan_scenario, params, gap=1e-9, fixed=first_stage, pinned=(n0, past),
                          pm_bounds=bounds)
        assert result.plan.objective == pytest.approx(reference.objective, rel=1e-7), hour
        fresh = RollingLP(case, params, op.first, result.plan_scenario)
        stale = RollingLP(case, params, op.first, result.plan_scenario)
        stale._data = {**stale._data, "c": stale._data["c"] + 1.0}  # as if the model's data had reached it
        for again in (fresh, stale):
            plan, surplus = again.solve(result.plan_scenario, pinned=(n0, past), pm_bounds=bounds)
            assert not surplus.any()
            for field in DISPATCH:
                np.testing.assert_array_equal(getattr(plan.dispatch, field), getattr(result.plan.dispatch, field))
        for name, field in PINNED.items():
            done[name][:, n0:n1] = np.asarray(getattr(result, field)).reshape(-1, k)
    assert any(not h.connected.all() for h in op.hours) and any(h.room is not None for h in op.hours)


def test_a_solution_within_the_solvers_tolerance_of_a_bound_is_read_as_given(case, first_stage):
    """HiGHS returns values within its feasibility tolerance (1e-7) of their bounds: a stored energy 1e-9 above the
    capacity is read as given (a day of a 100-agent fleet failed on it), and the cost terms read it too."""
    op = swinging(case, first_stage)
    lp = op._lp
    plan = op.operate_hour(1, [True])
    col = np.asarray(lp.h.getSolution().col_value).copy()
    stored = lp.columns.of(lp.lp.var["C"])
    col[stored[-1]] = case.storage.c_max + 1e-9
    arrays, costs = lp.lp.read(lp.columns, col)
    assert arrays["C"][0, -1] == case.storage.c_max + 1e-9
    assert math.isclose(sum(costs.values()), plan.plan.cost.total - plan.plan.cost.startup, rel_tol=1e-9)
