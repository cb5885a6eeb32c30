"""The Benders decomposition against the extensive form, and the validity of its cuts and of its relaxation."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cvxpy as cp
import numpy as np
import pytest

from microgrid_agent.checker import check_schedule
from microgrid_agent.solvers import benders
from microgrid_agent.solvers.benders import (
    STALL_MASTERS,
    Master,
    Stall,
    Subproblems,
    apart,
    first_stage_values,
    solve_decomposed,
)
from microgrid_agent.instance import make_instance
from microgrid_agent.model import DeviationCost, first_stage_variables, variables
from microgrid_agent.solvers.relaxation import group_means, group_relaxation, islanding_groups
from microgrid_agent.solvers.extensive import SolveError, solve
from microgrid_agent.solvers.highs import HIGHS_THREADS
from scenarios.case import HOURS, load_case

GAP = 0.005


@pytest.fixture(scope="module")
def small():
    return make_instance(load_case("paper"), scenarios=3, sample_size=3, subperiods=2, seed=2, island_hours=1)


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_benders_agrees_with_the_extensive_form_within_the_gap(small, workers):
    reference = small.solve(gap=1e-6)
    schedule = solve_decomposed(small.case, small.scen, small.params, gap=GAP, workers=workers)
    check_schedule(small.case, small.scen, schedule).raise_if_failed()
    assert schedule.bound <= reference.objective * (1 + 1e-6)
    assert schedule.objective >= reference.bound * (1 - 1e-6)
    assert schedule.mip_gap <= GAP + 1e-9
    assert schedule.objective <= reference.objective * (1 + GAP) + 1e-6


def test_every_route_reports_its_work_and_a_decomposition_step_by_step(small):
    """Simplex iterations and nodes beside the seconds (docs/solver.md, "What a solve reports"): the trace's rows add
    up to the decomposition's sums and those to the solve's work; LP masters have no nodes (a warm one whose new cuts
    its optimum meets has no simplex iterations either), an integer one at least its root; the extensive form reports
    its one MILP's. Every HiGHS ran on the pinned thread count."""
    schedule = solve_decomposed(small.case, small.scen, small.params, gap=GAP, workers=1)
    rows, sums, work = schedule.extra["trace"], schedule.extra["decomposition"], schedule.extra["work"]
    for k in benders.WORK:
        assert sums[k] == sum(r[k] for r in rows)
    assert work == {"simplex_iterations": sums["master_simplex_iterations"] + sums["subproblems_simplex_iterations"],
                    "nodes": sums["master_nodes"], "highs_threads": HIGHS_THREADS}
    assert rows[0]["master_simplex_iterations"] > 0 and rows[0]["subproblems_simplex_iterations"] > 0  # cold starts
    assert all(r["master_nodes"] == 0 for r in rows if r["phase"] == "lp")
    assert all(r["master_nodes"] >= 1 for r in rows if r["phase"] == "milp")
    extensive = small.solve(gap=GAP).extra
    assert extensive["method"] == "extensive" and extensive["work"]["simplex_iterations"] > 0
    assert extensive["work"]["nodes"] >= 1 and extensive["work"]["highs_threads"] == HIGHS_THREADS


@pytest.mark.slow  # a pool of two worker processes
def test_the_work_is_the_same_on_one_worker_or_two(small):
    """Each scenario keeps its own warm LP whichever worker holds it, so how they are spread changes no count."""
    one, two = (solve_decomposed(small.case, small.scen, small.params, gap=GAP, workers=w) for w in (1, 2))
    assert [{k: r[k] for k in ("lower_bound", "upper_bound", *benders.WORK)} for r in one.extra["trace"]] == \
        [{k: r[k] for k in ("lower_bound", "upper_bound", *benders.WORK)} for r in two.extra["trace"]]


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
        except SolveError:
            continue  # outside the region where every scenario is feasible: no cut claim to check
        assert np.all(q >= q0 + g0 @ (x - x0) - 1e-6 * np.abs(q))
        checked += 1
    assert checked >= 2


def _neighbours(master, count: int, seed: int = 0):
    """First stages near the master's LP optimum: the averaged neighbours stay in its convex LP region."""
    x0, _, _ = master.solve(relaxed=True, gap=1e-6, time_limit=None)
    rng = np.random.default_rng(seed)
    return [x0] + [0.5 * (np.clip(x0 + rng.uniform(-0.3, 0.3, x0.shape), 0, 1) + x0) for _ in range(count)]


def _master_with_cuts(inst, count: int = 3):
    """The instance's scenario LPs, and a master with their cuts at its LP optimum and ``count`` neighbours."""
    sub = Subproblems(inst.case, inst.scen, inst.params, range(inst.scen.S))
    master = Master(inst.case, inst.scen, inst.params)
    points = _neighbours(master, count)
    for x in points:
        master.add_cuts(x, *sub.evaluate(x))
    return sub, master, points


def _relaxation_value(inst, label, x) -> float:
    """sum_g p_g Q_hourly(x, mean data of g): the group relaxation with the first stage fixed at x."""
    v = variables(inst.case, int(label.max()) + 1, HOURS, first_stage="continuous")
    relaxation = group_relaxation(inst.case, inst.scen, inst.params, v, label)
    fixed = [v[name] == value for name, value in first_stage_values(v, x).items()]
    problem = cp.Problem(cp.Minimize(relaxation.probability @ relaxation.cost), relaxation.constraints + fixed)
    problem.solve(solver=cp.HIGHS)
    assert problem.status == cp.OPTIMAL
    return problem.value


@pytest.mark.parametrize("grouping", ["one group", "islanding"])
def test_group_relaxation_under_estimates_the_expected_recourse(small, grouping):
    """Jensen and hour-averaging: sum_g p_g Q_hourly(x, mean of g) <= sum_s p_s Q_s(x) at several first stages."""
    scen = small.scen
    label = np.zeros(scen.S, dtype=int) if grouping == "one group" else islanding_groups(scen)
    sub = Subproblems(small.case, scen, small.params, range(scen.S))
    checked = 0
    for x in _neighbours(Master(small.case, scen, small.params), 5):
        try:
            q, _ = sub.evaluate(x)
        except SolveError:
            continue  # outside the region where every scenario is feasible: no claim to check
        expected = float(scen.probability @ q)
        assert _relaxation_value(small, label, x) <= expected * (1 + 1e-7) + 1e-6
        checked += 1
    assert checked >= 2


def test_group_means_keep_the_expectation(small):
    """Each group's hourly mean data, weighted by p_g, is the expected hourly data; islanding groups keep U 0/1."""
    scen = small.scen
    label = islanding_groups(scen)
    means = group_means(scen, label)
    hourly = scen.load.reshape(scen.S, HOURS, scen.subperiods).mean(axis=2)
    assert np.isclose(means.probability.sum(), 1.0)
    assert np.allclose(means.probability @ means.load, scen.probability @ hourly)
    assert set(np.unique(means.connected)) <= {0.0, 1.0}


def test_a_regrouped_master_carries_the_cuts_and_the_incumbent_and_bounds_no_lower(small):
    """One relaxation group per islanding pattern: the same pool and cut rows, the incumbent as its MIP start, and
    an LP bound at least the one-group master's (finer groups under-estimate the recourse no less closely)."""
    sub, master, _ = _master_with_cuts(small)
    _, one_group, _ = master.solve(relaxed=True, gap=1e-6, time_limit=None)
    x, _, _ = master.solve(relaxed=False, gap=0.01, time_limit=None)  # any integer first stage will do
    master.remember(x, sub.evaluate(x)[0])
    label = islanding_groups(small.scen)
    assert label.max() > 0  # more than one pattern, or the test shows nothing
    other = master.regrouped(small.case, small.scen, small.params, label)
    assert other.pool is master.pool and list(other.active) == list(master.active)
    assert other.h.getNumRow() - other.base_rows == len(master.active)
    assert other.incumbent is not None and np.array_equal(other.incumbent[1], x)
    _, grouped, _ = other.solve(relaxed=True, gap=1e-6, time_limit=None)
    assert grouped >= one_group * (1 - 1e-7)


def test_a_search_stalls_once_after_masters_that_neither_find_a_better_schedule_nor_raise_the_bound():
    stall = Stall(gap=0.01)
    for lower in np.linspace(90.0, 90.09, STALL_MASTERS + 1):  # the bound rises by 0.09 < 0.1 x 1% of 100
        assert not stall.stalled()
        stall.after(lower, 100.0)
    assert stall.stalled() and not stall.stalled()  # said once
    rising, better = Stall(gap=0.01), Stall(gap=0.01)
    for i in range(3 * STALL_MASTERS):
        rising.after(90.0 + 0.02 * i, 100.0)  # 0.2 over ten masters
        better.after(90.0, 100.0 - 0.01 * i)
        assert not rising.stalled() and not better.stalled()


@pytest.mark.slow
def test_a_search_that_goes_on_regrouped_agrees_with_the_extensive_form(small, monkeypatch):
    """Made to stall before its first integer master, the search goes on with the grouped master and still
    certifies the gap against the extensive form's optimum; the trace shows where."""
    def at_once(stall):  # stalled at the first look, before the first integer master; never again
        stalled, stall.said = not stall.said, True
        return stalled

    monkeypatch.setattr(benders.Stall, "stalled", at_once)
    reference = small.solve(gap=1e-6)
    schedule = solve_decomposed(small.case, small.scen, small.params, gap=GAP, workers=1)
    check_schedule(small.case, small.scen, schedule).raise_if_failed()
    phases = [row["phase"] for row in schedule.extra["trace"]]
    assert phases.count("regroup") == 1 and phases[phases.index("regroup") - 1] == "lp"
    assert schedule.bound <= reference.objective * (1 + 1e-6)
    assert schedule.objective <= reference.objective * (1 + GAP) + 1e-6


def test_pruning_keeps_the_pool_and_the_master_optimum(small):
    """Pruning removes only slack rows: the pool keeps every cut and the master LP keeps its optimum."""
    sub, master, points = _master_with_cuts(small)
    _, before, _ = master.solve(relaxed=True, gap=1e-6, time_limit=None)
    master.prune()
    _, after, _ = master.solve(relaxed=True, gap=1e-6, time_limit=None)
    assert master.pool.size == len(points) * small.scen.S
    assert master.h.getNumRow() == master.base_rows + len(master.active)
    assert after == pytest.approx(before, rel=1e-7)


def test_the_master_allows_no_shut_down_that_ramps_cannot_reach():
    """G2 starts the day at 4 MW with P_min 1 MW and ramp-down 2.5 MW/h: at 10-minute steps it cannot reach
    its shut-down step (P_min + RD dt) by the end of hour 1, so no dispatch exists for a shut-down in hour 2,
    though the master's hourly relaxation (a whole hour's ramp in one step) would allow it. A shut-down in
    hour 3 is reachable and stays allowed."""
    inst = make_instance(load_case("paper"), scenarios=1, sample_size=1, subperiods=6, seed=0)
    units = [u.name for u in inst.case.units]
    g = units.index("G2")
    p0, p_min, rd = (inst.case.unit_array(k)[g] for k in ("initial_output", "p_min", "ramp_down"))
    assert rd + rd / 6 < p0 - p_min <= 2 * rd + rd / 6  # the case's numbers make hour 2 unreachable, hour 3 not

    def with_g2_off_from(hour: int) -> np.ndarray:
        commitment = np.ones((len(units), HOURS))
        commitment[g, hour - 1:] = 0
        return commitment

    def master_allows(commitment: np.ndarray) -> bool:
        master = Master(inst.case, inst.scen, inst.params)
        cols = master.x_cols[:commitment.size]  # I comes first in x, flattened column-major
        values = commitment.flatten(order="F")
        master.h.changeColsBounds(len(cols), cols.astype(np.int32), values, values)
        try:
            master.solve(relaxed=True, gap=1e-6, time_limit=None)
        except SolveError:
            return False
        return True

    assert not master_allows(with_g2_off_from(2))
    assert master_allows(with_g2_off_from(3))
    with pytest.raises(SolveError):  # the 10-minute model itself has no dispatch for it
        solve(inst.case, inst.scen, inst.params, fixed={"I": with_g2_off_from(2)})
    assert solve(inst.case, inst.scen, inst.params, fixed={"I": with_g2_off_from(3)}, gap=0.05).objective > 0


def test_the_relative_gap_is_closed_only_when_the_bound_reaches_a_zero_cost():
    assert apart(5_940.0, 6_000.0) == pytest.approx(0.01)
    assert apart(-1.0, np.inf) == np.inf
    assert apart(0.0, 0.0) == 0.0  # a microgrid that imports free energy: no division by zero
    assert apart(-1e-3, 0.0) == np.inf


@pytest.mark.slow
def test_benders_agrees_with_the_extensive_form_under_an_announced_rule(small):
    """The decomposition is built from the same model functions, the rule's dC included."""
    pieces = [[(-20.0, 0.0), (0.0, 0.0), (90.0, -45.0)]] * HOURS  # a dead band of 0.5 MW above, a charge below
    params = replace(small.params, deviation_cost=DeviationCost.from_pieces(pieces))
    reference = solve(small.case, small.scen, params, gap=1e-6)
    schedule = solve_decomposed(small.case, small.scen, params, gap=GAP, workers=1)
    check_schedule(small.case, small.scen, schedule, p_sch=params.p_sch,
                   deviation_cost=params.deviation_cost).raise_if_failed()
    assert reference.bound * (1 - 1e-6) <= schedule.objective <= reference.objective * (1 + GAP) + 1e-6
    assert schedule.bound <= reference.objective * (1 + 1e-6) and schedule.cost.penalty > 0


@pytest.mark.slow
def test_benders_agrees_with_the_extensive_form_when_the_award_must_be_taken(small):
    """The floor P_M >= U P_sch - dP- and its price reach the master's relaxation and the scenario LPs alike."""
    params = replace(small.params, penalty=np.inf, take_award=True)
    reference = solve(small.case, small.scen, params, gap=1e-6)
    schedule = solve_decomposed(small.case, small.scen, params, gap=GAP, workers=1)
    check_schedule(small.case, small.scen, schedule, p_sch=params.p_sch).raise_if_failed()
    assert reference.bound * (1 - 1e-6) <= schedule.objective <= reference.objective * (1 + GAP) + 1e-6
    connected = small.scen.connected > 0
    award = np.broadcast_to(np.repeat(params.p_sch, small.scen.subperiods), connected.shape)
    # this microgrid can absorb its award in every sub-period: P_M = P_sch wherever connected, nothing refused
    assert np.abs(schedule.dispatch.p_m - award)[connected].max() < 1e-6
    assert schedule.take_award and schedule.cost.penalty == pytest.approx(0.0, abs=1e-6)


@pytest.mark.slow
def test_a_start_from_another_day_is_the_first_incumbent_and_one_the_master_forbids_is_set_aside(small):
    """The day before's first stage, evaluated once the LP phase ends, is the search's first upper bound (its
    expected cost on today's scenarios, as the extensive form fixed to it gives it); a start that breaks a
    first-stage constraint changes nothing. Either way the answer is certified within the gap."""
    yesterday = make_instance(small.case, scenarios=3, sample_size=3, subperiods=2, seed=5, island_hours=1)
    start = yesterday.solve(gap=0.01).first
    reference = small.solve(gap=1e-6)
    its_cost = solve(small.case, small.scen, small.params, fixed=first_stage_variables(start), gap=1e-9).objective
    forbidden = replace(start, startup=np.zeros_like(start.startup), commitment=np.ones_like(start.commitment))
    forbidden = replace(forbidden, shutdown=np.ones_like(start.shutdown))  # shut down while committed all day
    for first, taken in ((start, True), (forbidden, False)):
        schedule = solve_decomposed(small.case, small.scen, small.params, gap=GAP, workers=1, start=first)
        rows = schedule.extra["trace"]
        phases = [r["phase"] for r in rows]
        at = phases.index("start" if taken else "start_set_aside")
        assert set(phases[:at]) == {"lp"} and set(phases[at + 1:]) == {"milp"}
        assert schedule.extra["decomposition"]["iterations"] == len(rows) - 1  # the start solved no master
        assert (rows[at]["upper_bound"] == pytest.approx(its_cost, rel=1e-6)) == taken
        check_schedule(small.case, small.scen, schedule).raise_if_failed()
        assert reference.bound * (1 - 1e-6) <= schedule.objective <= reference.objective * (1 + GAP) + 1e-6
        assert schedule.objective <= its_cost * (1 + 1e-9)  # never worse than where it started


# A decomposed solve's scenario pool on two worker processes, their pids said, and then a long wait.
POOL = """
import sys, time
from microgrid_agent.instance import make_instance
from microgrid_agent.solvers.benders import ScenarioPool
from scenarios.case import load_case
small = make_instance(load_case("paper"), scenarios=3, sample_size=3, subperiods=2, seed=2, island_hours=1)
pool = ScenarioPool(small.case, small.scen, small.params, 2)
print("workers", *(p.pid for p in pool.procs), flush=True)
time.sleep(600)
"""


@pytest.mark.slow
def test_the_workers_of_a_decomposed_solve_die_with_the_process_that_solves(gone):
    """SIGTERM ends ``dmosim solve`` (or a benchmark) at once; its workers, waiting on their pipes, must not stay."""
    solver = subprocess.Popen([sys.executable, "-c", POOL], stdout=subprocess.PIPE, text=True,
                              env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])})
    workers = []
    try:
        workers = next([int(pid) for pid in line.split()[1:]] for line in solver.stdout if line.startswith("workers "))
        solver.terminate()
        solver.wait()
        assert len(workers) == 2 and all(gone(pid) for pid in workers)
    finally:
        solver.kill()
        solver.wait()
        for pid in workers:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
