"""A schedule's first stage evaluated on fresh scenarios (microgrid_agent/solvers/evaluation.py): the estimate is
the extensive form's own value of that first stage on those scenarios, in one process or several."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dmosim.cli import main
from microgrid_agent.instance import make_instance
from microgrid_agent.model import first_stage_of
from microgrid_agent.solvers.evaluation import (Evaluation, estimate, evaluate_schedule, fresh_seed, lower_bound,
                                                optimality_gap, replication_seed)
from microgrid_agent.solvers.extensive import solve
from scenarios.case import load_case
from scenarios.generation import sample


@pytest.fixture(scope="module")
def solved():
    """A schedule whose first stage is evaluated: any will do, so it is solved to 1%, not to optimality (3x faster)."""
    inst = make_instance(load_case("paper"), scenarios=3, subperiods=1, island_hours=1, seed=5)
    return inst, inst.solve(method="extensive", gap=0.01)


def test_the_estimate_is_the_first_stage_s_value_on_the_fresh_scenarios(solved):
    inst, schedule = solved
    fresh = sample(inst.case, 12, 1, island_hours=1, seed=fresh_seed(5))
    one = evaluate_schedule(inst.case, schedule, inst.params, fresh)
    fixed = solve(inst.case, fresh, inst.params, fixed=first_stage_of(schedule), gap=1e-9)  # an LP: x is fixed
    assert one.expected_cost == pytest.approx(fixed.objective, rel=1e-7)
    assert one.scenarios == 12 and one.std_error > 0 and one.low < one.expected_cost < one.high
    assert one.high - one.expected_cost == pytest.approx(1.959964 * one.std_error, rel=1e-6)
    with pytest.raises(ValueError, match="at least 2 scenarios"):
        evaluate_schedule(inst.case, schedule, inst.params, fresh.single(0))


@pytest.mark.slow  # the subproblems go to two worker processes
def test_the_estimate_is_the_same_on_worker_processes(solved):
    inst, schedule = solved
    fresh = sample(inst.case, 12, 1, island_hours=1, seed=fresh_seed(5))
    one = evaluate_schedule(inst.case, schedule, inst.params, fresh)
    two = evaluate_schedule(inst.case, schedule, inst.params, fresh, workers=2)
    assert two.expected_cost == pytest.approx(one.expected_cost, rel=1e-9)


def test_fresh_scenarios_are_not_the_schedule_s_own():
    assert fresh_seed(0) != 0 and fresh_seed(0) != fresh_seed(1) and fresh_seed(3) == fresh_seed(3)
    seeds = {replication_seed(0, r) for r in range(5)} | {fresh_seed(0), 0}
    assert len(seeds) == 7  # replications draw apart from each other, the schedule and the evaluation


def test_the_stratified_estimate_weights_each_stratum_by_its_mass_and_its_own_variance():
    costs = np.array([1.0, 3.0, 10.0, 14.0, 20.0])
    stratum = np.array([0, 0, 1, 1, 1])
    probability = np.array([0.25, 0.25, 0.5 / 3, 0.5 / 3, 0.5 / 3])  # two strata of mass 1/2
    mean, error = estimate(costs, probability, stratum)
    assert mean == pytest.approx(0.5 * 2.0 + 0.5 * 44 / 3)
    assert error == pytest.approx(np.sqrt(0.25 * 2.0 / 2 + 0.25 * np.var([10, 14, 20], ddof=1) / 3))
    plain = estimate(costs, np.full(5, 0.2))
    assert plain == pytest.approx((costs.mean(), costs.std(ddof=1) / np.sqrt(5)))
    # a stratum with one member has no variance of its own: the plain error, which is the larger
    assert estimate(costs, probability, np.array([0, 1, 1, 1, 1]))[1] == pytest.approx(costs.std(ddof=1) / np.sqrt(5))


def test_the_lower_bound_and_the_gap_follow_mak_morton_and_wood():
    lower = lower_bound([100.0, 104.0, 96.0, 100.0], scenarios=5, seconds=1.0)
    error = np.std([100, 104, 96, 100], ddof=1) / 2
    assert lower.estimate == 100.0 and lower.std_error == pytest.approx(error)
    assert lower.low == pytest.approx(100.0 - 2.353363 * error, rel=1e-6)  # t(0.95, 3 degrees of freedom)
    upper = Evaluation(scenarios=400, expected_cost=103.0, std_error=0.5, low=0, high=0, seconds=0)
    gap = optimality_gap(upper, lower)
    assert gap["estimate"] == pytest.approx(3.0)
    assert gap["high"] == pytest.approx(3.0 + 1.644854 * 0.5 + 2.353363 * error, rel=1e-6)
    assert gap["relative_high"] == pytest.approx(gap["high"] / 103.0)
    with pytest.raises(ValueError, match="at least 2 replications"):
        lower_bound([1.0], scenarios=5, seconds=0)


def test_solve_reports_a_statistical_bound_and_the_schedule_s_gap(capsys):
    flags = ["solve", "--subperiods", "1", "--scenarios", "1", "--gap", "0.01", "--workers", "1"]
    assert main([*flags, "--evaluate", "20", "--replications", "2", "--islanding", "stratified", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    bound, gap = out["replications"], out["optimality_gap"]
    assert bound["replications"] == 2 and len(bound["bounds"]) == 2 and bound["low"] < bound["estimate"]
    assert gap["estimate"] == pytest.approx(out["evaluation"]["expected_cost"] - bound["estimate"])
    assert gap["high"] > max(gap["estimate"], 0)
    assert main([*flags, "--replications", "1"]) == 2
    assert "argument --replications: expected an integer in 2..100, got '1'" in capsys.readouterr().err
