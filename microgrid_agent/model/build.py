"""The stochastic market-based schedule as one cvxpy MILP: objective (1) subject to constraints (2)-(21).

First-stage (hourly) constraints and second-stage (per scenario and sub-period) constraints are assembled from
one function per constraint family (units.py, storage.py, loads.py, grid.py), so the extensive form here and the
decomposition's master and subproblems (solvers/) are built from the same code. docs/model.md maps each equation
to the function that builds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet

from ..schedule import FirstStage, StochasticSchedule
from .grid import balance, grid_transfer
from .index import Index
from .loads import load_dispatch, load_states
from .objective import objective
from .params import Params
from .storage import storage_dispatch, storage_modes
from .units import commitment, shutdown_after_ramping_down, unit_dispatch
from .variables import variables

@dataclass
class Model:
    """The built problem and its variables, for the solver and the result extraction."""

    problem: cp.Problem
    var: dict[str, cp.Variable]
    case: Case
    scen: ScenarioSet
    params: Params
    terms: dict[str, cp.Expression]


def first_stage_constraints(case: Case, v: dict, dt: float) -> list[cp.Constraint]:
    """The hourly decisions' own constraints: (6)-(7), (10), (13)-(14), the load windows and (17), and the
    shut-downs that ramps (5) at sub-period length ``dt`` (hours) allow."""
    cons = commitment(case, v) + shutdown_after_ramping_down(case, v, dt)
    if case.storage is not None:
        cons += storage_modes(case, v)
    if case.loads:
        cons += load_states(case, v)
    return cons


def second_stage_constraints(case: Case, scen, params: Params, ix: Index, v: dict) -> list[cp.Constraint]:
    """Per scenario and sub-period: (2)-(5), (8)-(9), (11)-(12), (15)-(16), (18)-(21)."""
    cons = unit_dispatch(case, ix, v) + balance(case, scen, ix, v) + grid_transfer(case, scen, params, ix, v)
    if case.storage is not None:
        cons += storage_dispatch(case, ix, v)
    if case.loads:
        cons += load_dispatch(case, ix, v)
    return cons


def build(case: Case, scen: ScenarioSet, params: Params, fixed: dict[str, np.ndarray] | None = None,
          pinned: tuple[int, dict[str, np.ndarray]] | None = None,
          pm_bounds: tuple[int, np.ndarray, np.ndarray] | None = None) -> Model:
    """Build objective (1) s.t. (2)-(21) for the scenario set.

    ``fixed`` pins first-stage variables by name (``I``, ``u``, ``v``, ``z``), e.g. to evaluate a given commitment
    (VSS, brute force). ``pinned = (n0, values)`` pins second-stage variables (``P``, ``Pst``, ``D``...) in the
    sub-periods before n0 to values of their full shape: the past of a day being operated (agent/realtime.py).
    ``pm_bounds = (n0, lower, upper)`` holds P_M within [lower, upper] in the sub-periods n0, n0 + 1, ... (one per
    value): the feeder's operating envelope of the hour being operated (agent/realtime.py; docs/network.md).
    """
    ix = Index(scen.S, scen.subperiods)
    v = variables(case, scen.S, ix.N, params=params)
    cons = first_stage_constraints(case, v, ix.dt) + second_stage_constraints(case, scen, params, ix, v)
    for name, value in (fixed or {}).items():
        if name in v:
            cons.append(v[name] == np.asarray(value, float).reshape(v[name].shape))
    if pinned is not None and pinned[0] > 0:
        n0, values = pinned
        cons += [v[name][:, :n0] == np.asarray(value, float).reshape(v[name].shape)[:, :n0]
                 for name, value in values.items() if name in v]
    if pm_bounds is not None:
        n0, lower, upper = pm_bounds
        now = v["PM"][:, n0:n0 + len(lower)]
        cons += [now >= np.asarray(lower, float)[None, :], now <= np.asarray(upper, float)[None, :]]
    terms = objective(case, scen, params, ix, v)
    problem = cp.Problem(cp.Minimize(sum(terms.values())), cons)
    return Model(problem, v, case, scen, params, terms)


FIXABLE = ("I", "u", "v", "z")  # the first-stage decisions ``build``'s ``fixed`` pins; y and w follow from I


def first_stage_of(schedule: StochasticSchedule) -> dict[str, np.ndarray]:
    """The first-stage decisions of a schedule by model variable name, as ``build``'s ``fixed`` takes them."""
    return {name: value for name, value in first_stage_variables(schedule.first).items() if name in FIXABLE}


def first_stage_variables(first: FirstStage) -> dict[str, np.ndarray]:
    """Every first-stage variable of ``first`` by model name (``FIRST_STAGE``), start-ups and shut-downs included:
    what a decomposed solve takes as its start."""
    return {"I": first.commitment, "y": first.startup, "w": first.shutdown, "u": first.discharging,
            "v": first.charging, "z": first.load_on}
