"""A schedule's first stage evaluated on fresh scenarios (microgrid_agent/solvers/evaluation.py): the estimate is
the extensive form's own value of that first stage on those scenarios, in one process or several."""

from __future__ import annotations

import pytest

from microgrid_agent.instance import make_instance
from microgrid_agent.model import first_stage_of
from microgrid_agent.solvers.evaluation import evaluate_schedule, fresh_seed
from microgrid_agent.solvers.extensive import solve
from scenarios.case import load_case
from scenarios.generation import sample


@pytest.fixture(scope="module")
def solved():
    inst = make_instance(load_case("paper"), scenarios=3, subperiods=1, island_hours=1, seed=5)
    return inst, inst.solve(method="extensive", gap=1e-6)


def test_the_estimate_is_the_first_stage_s_value_on_the_fresh_scenarios(solved):
    inst, schedule = solved
    fresh = sample(inst.case, 12, 1, island_hours=1, seed=fresh_seed(5))
    one = evaluate_schedule(inst.case, schedule, inst.params, fresh)
    fixed = solve(inst.case, fresh, inst.params, fixed=first_stage_of(schedule), gap=1e-9)  # an LP: x is fixed
    assert one.expected_cost == pytest.approx(fixed.objective, rel=1e-7)
    assert one.scenarios == 12 and one.std_error > 0 and one.low < one.expected_cost < one.high
    assert one.high - one.expected_cost == pytest.approx(1.959964 * one.std_error, rel=1e-6)
    two = evaluate_schedule(inst.case, schedule, inst.params, fresh, workers=2)
    assert two.expected_cost == pytest.approx(one.expected_cost, rel=1e-9)
    with pytest.raises(ValueError, match="at least 2 scenarios"):
        evaluate_schedule(inst.case, schedule, inst.params, fresh.single(0))


def test_fresh_scenarios_are_not_the_schedule_s_own():
    assert fresh_seed(0) != 0 and fresh_seed(0) != fresh_seed(1) and fresh_seed(3) == fresh_seed(3)
