"""The variables of the model, named after the paper's nomenclature (docs/model.md, "Indices and shapes")."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from scenarios.case import Case
from scenarios.horizon import HOURS

from .params import Params

FIRST_STAGE = ("I", "y", "w", "u", "v", "z")  # hourly decisions shared by every scenario
SECOND_STAGE = ("P", "Pr", "Pst", "C", "D", "PM", "LS", "dP")  # per scenario and sub-period


def variables(case: Case, S: int, N: int, first_stage: str = "binary",
              params: Params | None = None) -> dict[str, cp.Variable]:
    """The variables of S scenarios over N sub-periods. First-stage ones are binary, or ``continuous`` in [0, 1]
    for a subproblem whose first stage the decomposition fixes through column bounds. ``y`` and ``w`` are the
    units' start-up and shut-down indicators (the paper's F counts their costs; it has no symbol for them).
    ``params``, when the model's grid constraints are built on these variables, adds those its mismatch form
    needs (``mismatch_variables``)."""
    G, R, Dn = len(case.units), len(case.renewables), len(case.loads)
    kind = {"boolean": True} if first_stage == "binary" else {"bounds": [0, 1]}
    v = {
        "I": cp.Variable((G, HOURS), name="I", **kind),
        "y": cp.Variable((G, HOURS), bounds=[0, 1], name="y"),
        "w": cp.Variable((G, HOURS), bounds=[0, 1], name="w"),
        "P": cp.Variable((G * S, N), name="P"),
        "PM": cp.Variable((S, N), name="P_M"),
        "dP": cp.Variable((S, N), nonneg=True, name="dP_plus"),
        "LS": cp.Variable((S, N), nonneg=True, name="LS"),
    }
    if R:
        v["Pr"] = cp.Variable((R * S, N), nonneg=True, name="P_r")
    if case.storage is not None:
        v["u"] = cp.Variable(HOURS, name="u", **kind)
        v["v"] = cp.Variable(HOURS, name="v", **kind)
        v["Pst"] = cp.Variable((S, N), name="P_st")
        v["C"] = cp.Variable((S, N), bounds=[0, case.storage.c_max], name="C")  # (12)
    if Dn:
        v["z"] = cp.Variable((Dn, HOURS), name="z", **kind)
        v["D"] = cp.Variable((Dn * S, N), name="D")
    if params is not None:
        v.update(mismatch_variables(params, (S, N)))
    return v


def mismatch_variables(params: Params, shape: tuple[int, int]) -> dict[str, cp.Variable]:
    """The (S, N) variables of the grid's mismatch that only some ``params`` use (model/grid.py, objective.py):
    ``dPm``, dP- >= 0, the award not taken while connected (``take_award``); ``dC``, the deviation cost of an
    announced rule's epigraph (``deviation_cost``); ``delta``, the indicator of the paper's big-M form (20)-(21)."""
    v = {}
    if params.take_award:
        v["dPm"] = cp.Variable(shape, nonneg=True, name="dP_minus")
    if params.deviation_cost is not None:
        v["dC"] = cp.Variable(shape, name="dC")
    elif np.isfinite(params.penalty) and params.mismatch == "big-m":
        v["delta"] = cp.Variable(shape, boolean=True)
    return v
