"""The power balance (2) and the main grid: transfer limits with islanding (18) and the mismatch against the award
(19)-(21)."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet
from scenarios.horizon import per_subperiod

from .index import Index
from .params import Params


def balance(case: Case, scen: ScenarioSet, ix: Index, v: dict) -> list[cp.Constraint]:
    """Power balance (2) per scenario and sub-period, with renewables as used (availability minus spill).

    Load curtailment LS (>= 0, with no upper bound: docs/model.md, "Conventions the paper leaves open") and
    renewable spill make every commitment feasible in every scenario. Scenario data (load, availability) enter
    only right-hand sides, so they may be cvxpy Parameters (solvers/benders.py).
    """
    supply = v["PM"] + v["LS"]
    demand = scen.load
    cons = []
    if case.units:
        supply = supply + ix.total(len(case.units)) @ v["P"]
    if case.renewables:
        R = len(case.renewables)
        supply = supply + ix.total(R) @ v["Pr"]
        cons.append(v["Pr"] <= _stacked(scen.renewable, R * ix.S, ix.N))
    if case.storage is not None:
        supply = supply + v["Pst"]
    if case.loads:
        demand = demand + ix.total(len(case.loads)) @ v["D"]
    return [supply == demand, *cons]


def _stacked(data, rows: int, n: int):
    """(M, S, N) scenario data as (M S, N) rows member-major; a Parameter already has that shape."""
    return data.reshape(rows, n) if isinstance(data, np.ndarray) else data


def grid_transfer(case: Case, scen: ScenarioSet, params: Params, ix: Index, v: dict) -> list[cp.Constraint]:
    """Main grid transfer (18) and its positive mismatch (19)-(21).

    (18): islanded (U = 0) forces P_M = 0. With ``params.deviation_cost`` (an announced settlement rule), the
    mismatch is priced by its epigraph dC >= slope_j (P_M - P^sch) + intercept_j instead, and dP+ takes no part.
    Otherwise the positive mismatch is modelled exactly as
    dP+ >= P_M - P^sch, dP+ >= 0 (minimised through its penalty); an infinite penalty becomes P_M <= P^sch
    wherever connected. ``mismatch="big-m"`` keeps the paper's indicator form (20)-(21), corrected so that it
    is exact (docs/model.md), to test that both give the same optimum.

    With ``params.take_award`` the award must also be taken while connected: P_M >= U P^sch - dP-, where the
    shortfall dP- >= 0 is the award the microgrid could not absorb in that sub-period (its load, storage and
    adjustable loads full, its committed units at P_min, its renewables spilled), priced at VOLL like shed load
    (objective.py). With an infinite penalty this is P_M = P^sch wherever the microgrid can absorb it.

    The variables only some forms use (dP-, dC, the big-M indicator) are made with the others, by
    ``variables.mismatch_variables``; this function only constrains them.
    """
    p_sch = ix.per_scenario(params.p_sch)
    PM, dP, U = v["PM"], v["dP"], scen.connected
    pm_max = case.grid.p_m_max
    limits = [PM <= pm_max * U, PM >= -pm_max * U]  # (18)
    if params.take_award:
        limits.append(PM >= cp.multiply(p_sch, U) - v["dPm"])
    if params.deviation_cost is not None:
        # The announced rule's price of the deviation (19), max_j slope_j d + intercept_j, by its epigraph dC.
        cost, d = params.deviation_cost, PM - p_sch
        return [*limits, *(v["dC"] >= cp.multiply(ix.per_scenario(cost.slope[:, j]), d)
                           + ix.per_scenario(cost.intercept[:, j]) for j in range(cost.slope.shape[1]))]
    if np.isinf(params.penalty):
        # P_M <= P^sch where connected (U = 1) and no limit beyond (18) where islanded (U = 0).
        return [*limits, PM <= pm_max - cp.multiply(pm_max - p_sch, U), dP == 0]
    if params.mismatch == "positive-part":
        return [*limits, dP >= PM - p_sch]
    delta = v["delta"]
    M = case.grid.p_m_max + np.abs(p_sch)
    mismatch = PM - p_sch  # (19)
    return [
        *limits,
        dP <= cp.multiply(M, delta),  # (20), with dP+ >= 0 in its bounds
        mismatch - dP <= cp.multiply(M, 1 - delta),  # (21)
        mismatch - dP >= -cp.multiply(M, 1 - delta),  # (21)
        mismatch <= cp.multiply(M, delta),  # delta = 0 only where the mismatch is not positive
    ]


def dp_plus_of(params: Params, subperiods: int, p_m: np.ndarray, dp: np.ndarray | None) -> np.ndarray:
    """ΔP+ (S, N) of a solved dispatch: the dP+ variable's value, or, where a rule's dC priced the mismatch and
    dP+ took no part, max(P_M - P^sch, 0) from P_M."""
    if params.deviation_cost is None:
        return dp
    return np.maximum(p_m - per_subperiod(params.p_sch, subperiods)[None, :], 0.0)
