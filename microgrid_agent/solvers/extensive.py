"""The extensive form: the whole model as one MILP in HiGHS, giving a StochasticSchedule with its certified bound."""

from __future__ import annotations

import time

import cvxpy as cp
import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet
from scenarios.horizon import HOURS

from ..model import Model, Params, build, dp_plus_of
from ..schedule import CostBreakdown, Dispatch, FirstStage, StochasticSchedule, Timings
from .highs import FEASIBLE, HIGHS_THREADS, work


class SolveError(RuntimeError):
    """The solver returned no usable schedule (infeasible, or no incumbent within the time limit)."""


def solve(
    case: Case,
    scen: ScenarioSet,
    params: Params,
    *,
    gap: float = 0.005,
    time_limit: float | None = None,
    fixed: dict[str, np.ndarray] | None = None,
    pinned: tuple[int, dict[str, np.ndarray]] | None = None,
    pm_bounds: tuple[int, np.ndarray, np.ndarray] | None = None,
    verbose: bool = False,
) -> StochasticSchedule:
    """Solve the extensive form to relative gap ``gap``; the bound is HiGHS's MIP dual bound (valid).
    ``fixed``, ``pinned`` and ``pm_bounds`` are as in ``model.build``."""
    start = time.perf_counter()
    model = build(case, scen, params, fixed, pinned, pm_bounds)
    return solve_model(model, start, gap=gap, time_limit=time_limit, verbose=verbose)


def solve_model(model: Model, start: float, *, gap: float = 0.005, time_limit: float | None = None,
                verbose: bool = False) -> StochasticSchedule:
    """Solve a built model (``solve``); its timings count from ``start`` (``time.perf_counter``). A model whose
    problem holds cvxpy Parameters is solved again after their values change without being compiled again
    (cvxpy keeps its compiled program): the bidding model at each price level (agent/bidding.py)."""
    case, scen, params = model.case, model.scen, model.params
    options = {"mip_rel_gap": gap, "threads": HIGHS_THREADS}
    if time_limit is not None:
        options["time_limit"] = float(time_limit)
    model.problem.solve(solver=cp.HIGHS, canon_backend="SCIPY", verbose=verbose, **options)
    total = time.perf_counter() - start
    stats = model.problem.solver_stats
    info = stats.extra_stats
    if model.problem.status in (cp.INFEASIBLE, cp.INFEASIBLE_INACCURATE, cp.UNBOUNDED):
        raise SolveError(f"the model is {model.problem.status}; check the case (first-stage constraints conflict)")
    if info is None or info.primal_solution_status != FEASIBLE:
        raise SolveError(f"no feasible schedule found (solver status {model.problem.status}, time limit {time_limit} s)")
    status = "optimal" if model.problem.status == cp.OPTIMAL else "time_limit"
    objective = float(model.problem.value)
    offset = objective - info.objective_function_value
    bound = float(info.mip_dual_bound) + offset if model.problem.is_mixed_integer() else objective
    solve_s = float(stats.solve_time)
    simplex_iterations, nodes = work(info)
    return StochasticSchedule(
        status=status,
        objective=objective,
        bound=min(bound, objective),
        cost=CostBreakdown(**{k: float(e.value) for k, e in model.terms.items()}),
        first=_first_stage(model),
        dispatch=_dispatch(model),
        probability=scen.probability.copy(),
        subperiods=scen.subperiods,
        penalty=params.penalty,
        cost_convention=params.cost_convention,
        timings=Timings(build_s=total - solve_s, solve_s=solve_s, total_s=total),
        unit_names=tuple(u.name for u in case.units),
        load_names=tuple(d.name for d in case.loads),
        take_award=params.take_award,
        extra={"method": "extensive",
               "work": {"simplex_iterations": simplex_iterations, "nodes": nodes, "highs_threads": HIGHS_THREADS}},
    )


def _value(model: Model, name: str, shape: tuple[int, ...], binary: bool = False) -> np.ndarray:
    var = model.var.get(name)
    if var is None:
        return np.zeros(shape)
    out = np.asarray(var.value, float).reshape(shape)
    return np.rint(out) if binary else out


def _first_stage(model: Model) -> FirstStage:
    G, Dn = len(model.case.units), len(model.case.loads)
    return FirstStage(
        commitment=_value(model, "I", (G, HOURS), binary=True),
        startup=_value(model, "y", (G, HOURS), binary=True),
        shutdown=_value(model, "w", (G, HOURS), binary=True),
        discharging=_value(model, "u", (HOURS,), binary=True),
        charging=_value(model, "v", (HOURS,), binary=True),
        load_on=_value(model, "z", (Dn, HOURS), binary=True),
    )


def _dispatch(model: Model) -> Dispatch:
    S, N = model.scen.S, model.scen.N
    G, R, Dn = len(model.case.units), len(model.case.renewables), len(model.case.loads)
    return Dispatch(
        p_unit=_value(model, "P", (G, S, N)),
        p_renewable=_value(model, "Pr", (R, S, N)),
        p_storage=_value(model, "Pst", (S, N)),
        soc=_value(model, "C", (S, N)),
        d_load=_value(model, "D", (Dn, S, N)),
        p_m=_value(model, "PM", (S, N)),
        load_shed=_value(model, "LS", (S, N)),
        dp_plus=dp_plus_of(model.params, model.scen.subperiods, _value(model, "PM", (S, N)),
                           None if model.params.deviation_cost else _value(model, "dP", (S, N))),
    )
