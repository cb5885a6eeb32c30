"""The extensive-form model on small instances: brute force, formulation equivalence, islanding, penalties, VSS/EVPI."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from microgrid_agent.checker import check_schedule
from microgrid_agent.instance import Instance, make_instance
from dmo.market.rules import BUILT_IN
from microgrid_agent.model import DeviationCost, Params
from microgrid_agent.solvers.extensive import solve
from microgrid_agent.metrics import stochastic_metrics
from scenarios.case import load_case, parse_case
from scenarios.generation import ScenarioSet

EXACT = 1e-7  # relative MIP gap for tests that compare optima
ACTIVE = 3  # hours with demand in the brute-force case


def verified(case, scen, params, gap=EXACT, **options):
    """Every solve a test makes is re-verified by the independent checker."""
    schedule = solve(case, scen, params, gap=gap, **options)
    check_schedule(case, scen, schedule, p_sch=params.p_sch, penalty=params.penalty).raise_if_failed()
    return schedule


def _unit(name, cost, p_min, p_max, startup, min_up=1, min_down=1):
    return {"name": name, "cost": cost, "p_min": p_min, "p_max": p_max, "min_up": min_up, "min_down": min_down,
            "ramp_up": 100.0, "ramp_down": 100.0, "startup_cost": startup, "initial_on": False}


def tiny_case(min_up=(1, 1)):
    """Two units, no storage, loads or renewables; demand only in the first ACTIVE hours, so any unit on later
    costs its minimum output for nothing and the optimum keeps later hours off."""
    load = [6.0, 9.0, 4.0] + [0.0] * 21
    return parse_case({
        "case": {"name": "tiny"},
        "grid": {"p_m_max": 3.0, "p_sch": [2.0] * 24, "penalty": 80.0, "voll": 1000.0, "iso_price": [0.0] * 24},
        "fixed_load": {"forecast": load},
        "uncertainty": {"load": 0.2},
        "units": [_unit("A", 20.0, 1.0, 5.0, 30.0, min_up=min_up[0]), _unit("B", 50.0, 0.5, 4.0, 5.0, min_up=min_up[1])],
    })


def tiny_scenarios(case):
    """Two scenarios at hourly resolution: one with load 10% high, one islanded in hour 2."""
    base = np.asarray(case.fixed_load.forecast)
    connected = np.ones((2, 24))
    connected[1, 1] = 0
    return ScenarioSet(1, np.array([0.6, 0.4]), np.vstack([base * 1.1, base]), np.zeros((0, 2, 24)), connected)


def merit_order_cost(case, scen, commitment, penalty):
    """Expected cost of a fixed commitment by merit order, hour by hour (independent of the model).

    With unlimited ramps and no storage, each hour and scenario is separate: committed units give their minimum,
    any surplus is exported for free, and the rest comes from the cheapest source: units at their cost, the
    award at no cost, extra import at the penalty, and curtailment at VOLL.
    """
    units = case.units
    startup = sum(u.startup_cost * np.maximum(np.diff(np.r_[float(u.initial_on), commitment[g]]), 0).sum()
                  for g, u in enumerate(units))
    total = 0.0
    for s, t in itertools.product(range(scen.S), range(24)):
        on = commitment[:, t] > 0
        need = scen.load[s, t] - sum(u.p_min for u, o in zip(units, on) if o)
        cost = sum(u.cost * u.p_min for u, o in zip(units, on) if o)
        grid = case.grid.p_m_max * scen.connected[s, t]
        award = min(case.grid.p_sch[t], grid)
        sources = [(u.cost, u.p_max - u.p_min) for u, o in zip(units, on) if o]
        sources += [(0.0, award), (penalty, grid - award), (case.grid.voll, np.inf)]
        for price, amount in sorted(sources):
            take = min(max(need, 0.0), amount)
            cost, need = cost + price * take, need - take
        total += scen.probability[s] * cost
    return total + startup


def feasible_min_up(row, min_up, initial=0.0):
    """A unit that starts stays on for min_up hours or until the end of the day."""
    starts = np.flatnonzero(np.diff(np.r_[initial, row]) > 0)
    return all(row[s:s + min_up].all() for s in starts)


def brute_force_best(case, scen, feasible) -> float:
    """The least merit-order cost over every commitment of the two units in the active hours that ``feasible``
    (a (2, 24) 0/1 array -> bool) admits."""
    best = np.inf
    for bits in itertools.product((0, 1), repeat=2 * ACTIVE):
        commitment = np.zeros((2, 24))
        commitment[:, :ACTIVE] = np.reshape(bits, (2, ACTIVE))
        if feasible(commitment):
            best = min(best, merit_order_cost(case, scen, commitment, case.grid.penalty))
    return best


@pytest.mark.parametrize("min_up", [(1, 1), (2, 1)])
def test_optimum_equals_brute_force_enumeration(min_up):
    case = tiny_case(min_up)
    scen = tiny_scenarios(case)
    params = Params(np.asarray(case.grid.p_sch), case.grid.penalty)
    best = brute_force_best(case, scen, lambda c: all(feasible_min_up(c[g], min_up[g]) for g in range(2)))
    schedule = verified(case, scen, params)
    assert schedule.objective == pytest.approx(best, rel=1e-6)
    assert schedule.commitment.iloc[ACTIVE:].to_numpy().sum() == 0


@pytest.mark.parametrize("method", ["benders", "tree"])
def test_the_decomposed_routes_find_the_brute_force_optimum(method):
    """Benders (iterated masters) and the tree (one branch-and-bound tree) reach the enumerated optimum, each
    schedule verified by the checker, each bound below it."""
    if method == "tree":
        pytest.importorskip("pyscipopt")
    case = tiny_case((2, 1))
    scen = tiny_scenarios(case)
    params = Params(np.asarray(case.grid.p_sch), case.grid.penalty)
    best = brute_force_best(case, scen, lambda c: feasible_min_up(c[0], 2) and feasible_min_up(c[1], 1))
    schedule = Instance(case, scen, params).solve(method=method, workers=1, gap=EXACT)
    check_schedule(case, scen, schedule, p_sch=params.p_sch, penalty=params.penalty).raise_if_failed()
    assert schedule.extra["method"] == method
    assert schedule.objective == pytest.approx(best, rel=1e-6) and schedule.bound <= best * (1 + 1e-6)


def test_a_unit_carried_across_midnight_keeps_the_state_its_minimum_time_still_asks_for():
    """B (dear, and not needed: A and the award cover the load) was started an hour before midnight and must run
    3 h: on in hours 1-2, by brute force too; free of that, it stops at midnight."""
    data = tiny_case((1, 3)).model_dump()
    data["fixed_load"]["forecast"] = [4.0, 5.0, 3.0] + [0.0] * 21
    data["units"][1].update(initial_on=True, initial_hours=1)
    case = parse_case(data)
    assert [u.keep_initial_hours for u in case.units] == [0, 2]
    scen = tiny_scenarios(case)
    params = Params(np.asarray(case.grid.p_sch), case.grid.penalty)
    best = brute_force_best(case, scen, lambda c: c[1, :2].all() and feasible_min_up(c[1], 3, initial=1.0))
    owing = verified(case, scen, params)
    assert owing.commitment["B"].iloc[:2].tolist() == [1, 1]
    assert owing.objective == pytest.approx(best, rel=1e-6)
    data["units"][1]["initial_hours"] = 3  # it has run long enough: free to stop at midnight
    free = verified(parse_case(data), scen, params)
    assert free.commitment["B"].iloc[0] == 0 and free.objective < owing.objective - 1.0
    # the checker holds a schedule to the hours still owed
    report = check_schedule(case, scen, free, p_sch=params.p_sch, penalty=params.penalty)
    assert not report.ok and "initial state" in report.summary(3)


def test_min_up_time_changes_the_brute_force_optimum():
    """The enumeration above must be sensitive to minimum up time, or it would not test it."""
    costs = [verified(tiny_case(m), tiny_scenarios(tiny_case(m)), Params(np.full(24, 2.0), 80.0)).objective
             for m in ((1, 1), (3, 3))]
    assert costs[1] > costs[0] + 1.0


# --- the mismatch term generalised to an announced settlement rule --------------------------------------------------

RULES = [("paper", {"penalty": 80.0, "credit": 15.0}),  # a credit below the cheapest unit: nothing to gain later
         ("symmetric", {"above": 60.0, "below": 25.0}),
         ("deadband", {"rate": 90.0, "below_rate": 15.0, "band_mw": 0.4, "band_share": 0.1}),
         ("price-linked", {"k": 2.0, "floor": 35.0})]


def rule_cost(case, name, params) -> DeviationCost:
    """The built-in rule's pieces, as the DMO's award carries them to the agent."""
    prices = [10.0 * (t % 5) for t in range(24)]
    return DeviationCost.from_pieces(BUILT_IN[name].deviation_cost(params, case.grid.p_sch, prices))


def rule_merit_order_cost(case, scen, commitment, cost: DeviationCost, islanded_free: bool = False) -> float:
    """Expected cost of a fixed commitment when the import x is priced by the rule, f(x - P_sch) (independent of the
    model): each hour and scenario alone, the least of units' merit order + curtailment + f over x. That sum is
    piecewise linear and convex in x, so its least value is at a breakpoint: the ends of x's range, the rule's
    kinks, or where the merit order moves to the next unit. With ``islanded_free``, f costs nothing islanded."""
    units, total = case.units, 0.0
    startup = sum(u.startup_cost * np.maximum(np.diff(np.r_[float(u.initial_on), commitment[g]]), 0).sum()
                  for g, u in enumerate(units))
    for s, t in itertools.product(range(scen.S), range(24)):
        on = [u for u, o in zip(units, commitment[:, t] > 0) if o]
        need = scen.load[s, t] - sum(u.p_min for u in on)
        flexible = sorted((u.cost, u.p_max - u.p_min) for u in on)
        grid, award = case.grid.p_m_max * scen.connected[s, t], case.grid.p_sch[t]
        slope, intercept = cost.slope[t], cost.intercept[t]
        charged = not (islanded_free and scen.connected[s, t] == 0)
        f = lambda d: float(np.max(slope * d + intercept)) if charged else 0.0  # noqa: E731
        order = np.argsort(slope)
        kinks = [(intercept[a] - intercept[b]) / (slope[b] - slope[a]) for a, b in zip(order, order[1:])
                 if slope[b] > slope[a]]
        lo, hi = -grid, min(grid, need)
        candidates = [lo, hi, *(award + k for k in kinks), *(need - np.cumsum([c for _, c in flexible]))]

        def merit(r):
            out = 0.0
            for price, amount in flexible:
                take = min(max(r, 0.0), amount)
                out, r = out + price * take, r - take
            return out + case.grid.voll * max(r, 0.0)

        best = min(merit(need - x) + f(x - award) for x in candidates if lo - 1e-12 <= x <= hi + 1e-12)
        total += scen.probability[s] * (best + sum(u.cost * u.p_min for u in on))
    return total + startup


@pytest.mark.parametrize("name, params", RULES, ids=[r[0] for r in RULES])
def test_a_rules_optimum_equals_brute_force_and_the_checker_prices_it_alike(name, params):
    case = tiny_case()
    scen = tiny_scenarios(case)
    cost = rule_cost(case, name, params)
    params_ = Params(np.asarray(case.grid.p_sch), case.grid.penalty, deviation_cost=cost)
    best = np.inf
    for bits in itertools.product((0, 1), repeat=2 * ACTIVE):
        commitment = np.zeros((2, 24))
        commitment[:, :ACTIVE] = np.reshape(bits, (2, ACTIVE))
        best = min(best, rule_merit_order_cost(case, scen, commitment, cost))
    schedule = solve(case, scen, params_, gap=EXACT)
    report = check_schedule(case, scen, schedule, p_sch=params_.p_sch, deviation_cost=cost)
    report.raise_if_failed()
    assert schedule.objective == pytest.approx(best, rel=1e-6)
    assert report.cost.penalty == pytest.approx(schedule.cost.penalty, rel=1e-9, abs=1e-9)


def test_the_paper_rules_pieces_schedule_as_the_papers_own_term():
    case = tiny_case()
    scen = tiny_scenarios(case)
    cost = rule_cost(case, "paper", {"penalty": case.grid.penalty, "credit": 0.0})
    assert cost.paper_rate() == case.grid.penalty
    paper = verified(case, scen, Params(np.asarray(case.grid.p_sch), case.grid.penalty))
    pieces = solve(case, scen, Params(np.asarray(case.grid.p_sch), case.grid.penalty, deviation_cost=cost), gap=EXACT)
    assert pieces.objective == pytest.approx(paper.objective, rel=1e-9)
    assert rule_cost(case, "paper", {"penalty": 80.0, "credit": 5.0}).paper_rate() is None


@pytest.fixture(scope="module")
def paper_small():
    """The paper's case at hourly resolution with three scenarios, no reduction (same draws for every H)."""
    return lambda **kw: make_instance(load_case("paper"), scenarios=3, sample_size=3, subperiods=1, seed=4, **kw)


@pytest.mark.slow
def test_positive_part_matches_papers_big_m(paper_small):
    inst = paper_small(transfer_scale=0.6, penalty=150.0)
    exact = verified(inst.case, inst.scen, inst.params)
    big_m = verified(inst.case, inst.scen, replace(inst.params, mismatch="big-m"))
    assert exact.cost.penalty > 1.0, "the instance must actually deviate, or both formulations trivially agree"
    assert big_m.objective == pytest.approx(exact.objective, rel=1e-6)


def test_islanding_forces_zero_transfer_and_infinite_penalty_caps_import(paper_small):
    inst = paper_small(island_hours=2, penalty=float("inf"))
    schedule = verified(inst.case, inst.scen, inst.params, gap=0.01)  # any feasible schedule must (3x faster)
    islanded = inst.scen.connected == 0
    assert islanded.any()
    assert np.abs(schedule.dispatch.p_m[islanded]).max() <= 1e-7
    p_sch = np.broadcast_to(inst.params.p_sch, schedule.dispatch.p_m.shape)
    assert (schedule.dispatch.p_m <= p_sch + 1e-7).all()
    assert schedule.cost.penalty == 0.0


@pytest.mark.slow
def test_cheap_penalty_is_used_and_infinite_penalty_is_not(paper_small):
    low = paper_small(transfer_scale=0.5, penalty=10.0)
    cheap = verified(low.case, low.scen, low.params)
    assert (cheap.dispatch.p_m > low.params.p_sch + 1e-3).any() and cheap.cost.penalty > 0
    hard = paper_small(transfer_scale=0.5, penalty=float("inf"))
    capped = verified(hard.case, hard.scen, hard.params)
    assert (capped.dispatch.p_m <= hard.params.p_sch + 1e-7).all() and capped.cost.penalty == 0.0
    assert capped.objective > cheap.objective  # the award now binds where the cheap penalty was paid


def nondecreasing(costs):
    return all(b >= a * (1 - 1e-6) for a, b in zip(costs, costs[1:]))


@pytest.mark.slow
def test_cost_grows_with_penalty_and_islanding_hours(paper_small):
    by_penalty = [paper_small(transfer_scale=0.6, penalty=c) for c in (0.0, 50.0, 150.0, float("inf"))]
    costs = [verified(i.case, i.scen, i.params).objective for i in by_penalty]
    assert nondecreasing(costs) and costs[-1] > costs[0]
    by_hours = [paper_small(island_hours=h, penalty=float("inf")) for h in (0, 1, 3)]
    costs = [verified(i.case, i.scen, i.params).objective for i in by_hours]
    assert nondecreasing(costs) and costs[-1] > costs[0]


@pytest.mark.slow
def test_vss_and_evpi_are_non_negative(paper_small):
    inst = paper_small(island_hours=1)
    rp = verified(inst.case, inst.scen, inst.params)
    m = stochastic_metrics(inst, rp, gap=EXACT)
    tol = 1e-6 * abs(rp.objective)
    assert m.vss >= -tol
    assert m.evpi >= -tol
    assert m.ws <= m.rp <= m.eev


@pytest.mark.slow
def test_ten_minute_resolution_schedule_verifies():
    inst = make_instance(load_case("paper"), scenarios=2, sample_size=4, subperiods=6, seed=1)
    schedule = inst.solve(gap=0.02, time_limit=120)
    check_schedule(inst.case, inst.scen, schedule).raise_if_failed()
    assert schedule.dispatch.p_m.shape == (2, 144)
    assert schedule.mip_gap <= 0.02 + 1e-9
    assert schedule.bound <= schedule.objective


@pytest.mark.parametrize("penalty", [80.0, 0.0])
def test_an_award_that_must_be_taken_equals_brute_force(penalty):
    """Taken while connected: the award not absorbed costs VOLL, the import above it the penalty, and islanded
    hours nothing. The tiny case has no load after hour 3, so the award is refused there at VOLL in every
    commitment; at penalty 0, extra import is free, so only the floor separates the readings."""
    case = tiny_case()
    scen = tiny_scenarios(case)
    params = Params(np.asarray(case.grid.p_sch), penalty, take_award=True)
    as_rule = DeviationCost.from_pieces([[(-case.grid.voll, 0.0), (0.0, 0.0), (penalty, 0.0)]] * 24)
    best = np.inf
    for bits in itertools.product((0, 1), repeat=2 * ACTIVE):
        commitment = np.zeros((2, 24))
        commitment[:, :ACTIVE] = np.reshape(bits, (2, ACTIVE))
        best = min(best, rule_merit_order_cost(case, scen, commitment, as_rule, islanded_free=True))
    schedule = verified(case, scen, params)
    assert schedule.take_award and schedule.objective == pytest.approx(best, rel=1e-6)
    refused = case.grid.voll * 2.0 * (24 - ACTIVE)  # 2 MW in each hour without load, in both scenarios
    assert schedule.cost.penalty >= refused - 1e-6
    ceiling = verified(case, scen, replace(params, take_award=False))
    assert ceiling.objective < schedule.objective - refused + 1e-6
    # the checker prices the refused award itself: told the award was a ceiling, it finds a different cost
    assert not check_schedule(case, scen, schedule, p_sch=params.p_sch, penalty=penalty, take_award=False).ok
