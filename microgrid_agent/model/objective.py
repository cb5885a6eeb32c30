"""Objective (1): expected generation, start-up/shut-down, curtailment and penalty cost, by term."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet
from scenarios.horizon import per_subperiod

from ..schedule import energy_weight
from .index import Index
from .params import Params


def objective(case: Case, scen: ScenarioSet, params: Params, ix: Index, v: dict) -> dict[str, cp.Expression]:
    """Objective (1) by term: expected generation, start-up/shut-down, curtailment and penalty cost.

    Energy terms are MW x ``energy_weight`` (dt in the real convention); start-up and shut-down costs are
    counted once per transition, as part of F. With ``params.import_price`` (bidding), grid energy is priced too.
    The penalty term is c dP+, or with ``params.deviation_cost`` the announced rule's dC (grid.py); with
    ``params.take_award`` it also holds the award not taken, dP-, at VOLL.
    """
    ew = energy_weight(ix.K, params.cost_convention)
    pr = np.asarray(scen.probability, float)[:, None] * ew
    terms = {
        "generation": cp.sum(cp.multiply(np.tile(pr, (len(case.units), ix.N)) * ix.per_row(case.unit_array("cost")), v["P"])),
        "startup": startup_cost(case, v),
        "curtailment": cp.sum(cp.multiply(pr * case.grid.voll, v["LS"])),
        "penalty": cp.Constant(0.0),
    }
    if params.deviation_cost is not None:
        terms["penalty"] = cp.sum(cp.multiply(np.tile(pr, (1, ix.N)), v["dC"]))
    elif np.isfinite(params.penalty):
        terms["penalty"] = cp.sum(cp.multiply(pr * params.penalty, v["dP"]))
    if params.take_award:
        terms["penalty"] = terms["penalty"] + cp.sum(cp.multiply(pr * case.grid.voll, v["dPm"]))
    if params.import_price is not None:
        terms["energy"] = cp.sum(cp.multiply(pr * per_subperiod(params.import_price, ix.K), v["PM"]))
    return terms


def startup_cost(case: Case, v: dict) -> cp.Expression:
    """The first-stage part of F in (1): start-up and shut-down costs, once per transition."""
    return cp.sum(case.unit_array("startup_cost") @ v["y"] + case.unit_array("shutdown_cost") @ v["w"])


def recourse(case: Case, scen: ScenarioSet, params: Params, ix: Index, v: dict) -> dict[str, cp.Expression]:
    """Objective (1) without its first-stage start-up term: the cost of the second stage, by term."""
    terms = objective(case, scen, params, ix, v)
    del terms["startup"]
    return terms
