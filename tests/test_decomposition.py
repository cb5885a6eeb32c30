"""The Benders decomposition against the extensive form, and the validity of its cuts."""

from __future__ import annotations

import numpy as np
import pytest

from microgrid_agent.checker import check_schedule
from microgrid_agent.decomposition import Master, Subproblems, solve_decomposed
from microgrid_agent.instance import make_instance
from scenarios.case import load_case

GAP = 0.005


@pytest.fixture(scope="module")
def small():
    return make_instance(load_case("paper"), scenarios=3, sample_size=3, subperiods=2, seed=2, island_hours=1)


@pytest.mark.parametrize("workers", [1, 2])
def test_benders_agrees_with_the_extensive_form_within_the_gap(small, workers):
    reference = small.solve(gap=1e-6)
    schedule = solve_decomposed(small.case, small.scen, small.params, gap=GAP, workers=workers)
    check_schedule(small.case, small.scen, schedule).raise_if_failed()
    assert schedule.bound <= reference.objective * (1 + 1e-6)
    assert schedule.objective >= reference.bound * (1 - 1e-6)
    assert schedule.mip_gap <= GAP + 1e-9
    assert schedule.objective <= reference.objective * (1 + GAP) + 1e-6


def test_cuts_under_estimate_the_scenario_cost(small):
    """theta_s >= Q_s(x^) + g (x - x^) must hold at any other first stage x: check it at random neighbours."""
    sub = Subproblems(small.case, small.scen, small.params, range(small.scen.S))
    master = Master(small.case, small.scen, small.params)
    x0, _, _ = master.solve(relaxed=True, gap=1e-6, time_limit=None)
    q0, g0 = sub.evaluate(x0)
    rng = np.random.default_rng(0)
    checked = 0
    for _ in range(6):
        x = np.clip(x0 + rng.uniform(-0.3, 0.3, x0.shape), 0, 1)
        # a neighbour the master accepts: average with x0 stays inside the master's convex LP region
        x = 0.5 * (x + x0)
        try:
            q, _ = sub.evaluate(x)
        except Exception:
            continue  # outside the region where every scenario is feasible: no cut claim to check
        assert np.all(q >= q0 + g0 @ (x - x0) - 1e-6 * np.abs(q))
        checked += 1
    assert checked >= 2
