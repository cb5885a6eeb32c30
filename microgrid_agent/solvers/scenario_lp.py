"""One scenario's second stage as an LP, built once by cvxpy with the scenario's data as Parameters.

Given the first stage x, one scenario is an LP: objective (1) without start-up costs, constraints (2)-(5), (8)-(9),
(11)-(12), (15)-(16), (18)-(21). The Benders subproblems (benders.py) compile it once per scenario and re-solve it
warm as x changes; the rolling real-time LP (rolling.py) compiles it once per day and re-solves it each hour with
that hour's data. Both read the solution back through the same column map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cvxpy as cp
import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet

from ..model import FIRST_STAGE, SECOND_STAGE, Index, Params, recourse, second_stage_constraints, variables
from .highs import Columns, compile_problem


@dataclass
class OneScenario:
    """One scenario's data as cvxpy Parameters, so the compiled LP is re-used for every scenario."""

    subperiods: int
    load: cp.Parameter
    renewable: cp.Parameter
    connected: cp.Parameter
    probability: np.ndarray = field(default_factory=lambda: np.ones(1))
    S: int = 1

    def set(self, scen: ScenarioSet, s: int) -> None:
        self.load.value = scen.load[s:s + 1]
        # a case without renewables has none to set; its parameter is one row the model never reads
        self.renewable.value = scen.renewable[:, s] if len(scen.renewable) else np.zeros(self.renewable.shape)
        self.connected.value = scen.connected[s:s + 1]


class ScenarioLP:
    """The second stage of one scenario at ``subperiods`` sub-periods an hour, the first stage as continuous
    variables (fixed by column bounds); ``compile`` gives HiGHS-ready data for one scenario of a set."""

    def __init__(self, case: Case, params: Params, subperiods: int, n: int):
        R = len(case.renewables)
        self.one = OneScenario(subperiods, cp.Parameter((1, n)), cp.Parameter((max(R, 1), n)), cp.Parameter((1, n)))
        v = variables(case, 1, n, first_stage="continuous", params=params)
        ix = Index(1, subperiods)
        self.terms = recourse(case, self.one, params, ix, v)  # start-ups are first-stage: the master carries them
        self.problem = cp.Problem(cp.Minimize(sum(self.terms.values())),
                                  second_stage_constraints(case, self.one, params, ix, v))
        self.var = v

    def compile(self, scen: ScenarioSet, s: int) -> tuple[dict, Columns]:
        """The LP's data with scenario ``s`` of ``scen`` (re-applying the Parameters: about 2 ms), and its columns."""
        self.one.set(scen, s)
        return compile_problem(self.problem)

    def first_stage(self, columns: Columns) -> tuple[np.ndarray, np.ndarray]:
        """Where the flat first stage x (FIRST_STAGE order, as ``benders.first_stage_vector`` lays it out) meets
        the LP: which entries of x it holds, and their columns. A first-stage variable the LP does not meet (the
        start-up indicators, once ramps are scaled by the commitment) has a zero subgradient."""
        first = [self.var[n] for n in FIRST_STAGE if n in self.var]
        held = np.concatenate([np.full(var.size, columns.holds(var)) for var in first])
        cols = np.concatenate([columns.of(var) for var in first if columns.holds(var)])
        return held, cols

    def read(self, columns: Columns, col: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """A solution's second-stage values by name and its cost terms by name. Values are taken as the solver gives
        them, within its feasibility tolerance of their bounds (as cvxpy takes a solution: ``save_value``; setting
        ``value`` refuses a stored energy 1e-9 above its capacity)."""
        for var in self.var.values():  # every variable of the LP, so that each cost term has its value
            if columns.holds(var):
                var.save_value(columns.value(var, col))
        arrays = {n: self.var[n].value for n in SECOND_STAGE if n in self.var and columns.holds(self.var[n])}
        return arrays, {name: float(term.value) for name, term in self.terms.items()}
