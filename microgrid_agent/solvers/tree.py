"""Branch-and-Benders-cut: the decomposition of benders.py solved in one branch-and-bound tree (SCIP, through
PySCIPOpt), so that no master is solved twice.

The master and its LP-phase cuts are benders.py's (``Master``, ``relax``); it goes to SCIP as it stands (an MPS file
HiGHS writes), and a constraint handler holds the scenarios: at every integer candidate, from the tree's LP or from
SCIP's heuristics, it evaluates the first stage x on the scenario LPs (``ScenarioPool``, warm HiGHS models on
``--workers`` processes, each x once) and either accepts the candidate (theta_s >= Q_s(x) for every s) or, at a
node's LP solution, adds the violated scenarios' optimality cuts theta_s >= Q_s(x^) + g_s (x - x^) to the tree as
global rows. A candidate whose master value already reaches the best schedule's is refused unevaluated: whatever its
recourse, it cannot improve on it. Every x evaluated that beats the best so far is handed to SCIP with theta_s =
Q_s(x), a feasible solution, so its primal bound prunes the tree. SCIP stops at the target gap; its dual bound is
valid because the cuts and the master's relaxation under-estimate the recourse. docs/solver.md has the
measurements.

PySCIPOpt is an optional dependency (``pip install 'dmosim[scip]'``).
"""

from __future__ import annotations

import os
import tempfile
import time

import highspy
import numpy as np

from scenarios import exact
from scenarios.case import Case
from scenarios.generation import ScenarioSet

from ..model import Params
from ..schedule import StochasticSchedule
from .benders import (Found, Master, ScenarioPool, Trace, apart, decomposition, first_stage_values, relax, reporter,
                      schedule_of)
from .extensive import SolveError
from .routes import SCIP_INSTALL

_TOLERANCE = 1e-6  # relative: theta_s below Q_s(x) by more than this (times 1 + |Q_s|) is a violated cut


def solve_tree(case: Case, scen: ScenarioSet, params: Params, *, gap: float = 0.005, time_limit: float | None = None,
               workers: int = 2, progress=None) -> StochasticSchedule:
    """The decomposition to a certified relative gap in one SCIP tree; the same StochasticSchedule as the others."""
    try:
        import pyscipopt  # noqa: PLC0415  (optional)
    except ImportError as exc:
        raise SolveError(f"the tree method needs PySCIPOpt: {SCIP_INSTALL}") from exc
    start = time.perf_counter()
    deadline = start + time_limit if time_limit else None
    with decomposition(case, scen, params, workers) as (master, pool, trace):
        relax(master, pool, trace, deadline, reporter(progress, trace, start), gap=gap)
        built = time.perf_counter()
        tree = _Tree(pyscipopt, master, pool, trace)
        trace.build_s += time.perf_counter() - built  # the master as a SCIP model
        remaining = None if deadline is None else max(1.0, deadline - time.perf_counter())
        lower, status = tree.solve(gap, remaining, progress, start)
        if tree.best is None:
            raise SolveError(f"the tree found no schedule ({status})")
        arrays, costs = pool.dispatch(tree.best)
    best = tree.best
    found = Found(first_stage_values(master.var, best), master.first_stage_cost(best), arrays, costs,
                  min(lower, tree.value), status)
    return schedule_of(case, scen, params, found, trace, time.perf_counter() - start, "tree")


class _Tree:
    """The master as a SCIP model, with the scenarios as a constraint handler; ``best`` and ``value``: the best first
    stage evaluated and its expected cost."""

    def __init__(self, scip, master: Master, pool: ScenarioPool, trace: Trace):
        self.scip, self.master, self.pool, self.trace = scip, master, pool, trace
        self.best, self.value = None, np.inf
        self.evaluated: dict[bytes, tuple[np.ndarray, np.ndarray | None]] = {}  # x -> Q_s(x), g_s (None: no x)
        self.evaluation_s = 0.0
        self.model = m = scip.Model()
        m.hideOutput()
        h = master.h
        n = h.getNumCol()
        h.changeColsIntegrality(len(master.binary), master.binary,
                                np.array([highspy.HighsVarType.kInteger] * len(master.binary)))
        for j in range(n):
            h.passColName(j, f"c{j}")
        with tempfile.TemporaryDirectory(prefix="dmosim-tree-") as directory:
            path = os.path.join(directory, "master.mps")
            h.writeModel(path)
            m.readProblem(path)
        by_name = {v.name: v for v in m.getVars()}
        self.columns = [by_name[f"c{j}"] for j in range(n)]
        self.x = [self.columns[j] for j in master.x_cols]
        self.theta = [self.columns[j] for j in master.theta_cols]

    def solve(self, gap: float, time_limit: float | None, progress, start: float) -> tuple[float, str]:
        """Solve to ``gap``; SCIP's dual bound and the status (optimal, or time_limit)."""
        m = self.model
        handler = _handler_class(self.scip)(self)
        m.includeConshdlr(handler, "scenarios", "Benders optimality cuts of the scenario LPs",
                          enfopriority=-1, chckpriority=-2_000_000)  # after integrality; after the master's rows
        m.addPyCons(m.createCons(handler, "scenarios"))
        m.setRealParam("limits/gap", gap)
        if time_limit is not None:
            m.setRealParam("limits/time", float(time_limit))
        # The scenario rows are hidden from presolving, so it may not fix variables by dual arguments.
        m.setBoolParam("misc/allowstrongdualreds", False)
        m.setBoolParam("misc/allowweakdualreds", False)
        t0, before = time.perf_counter(), self.pool.simplex_iterations
        m.optimize()
        tree_s = time.perf_counter() - t0
        # the master's work here is SCIP's: the simplex iterations of its LPs and its nodes
        self.trace.add("tree", m.getDualbound(), self.value, tree_s - self.evaluation_s, self.evaluation_s,
                       (m.getNLPIterations(), m.getNNodes()), self.pool.simplex_iterations - before)
        if progress:
            progress(f"tree: bound {m.getDualbound():,.2f}, best {self.value:,.2f} "
                     f"({apart(m.getDualbound(), self.value):.2%} apart), {m.getNNodes()} nodes, "
                     f"{len(self.evaluated)} first stages evaluated, {time.perf_counter() - start:.0f} s in all")
        return m.getDualbound(), "time_limit" if m.getStatus() == "timelimit" else "optimal"

    def recourse(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, bool]:
        """Q_s(x), the subgradients (None: no recourse, x breaks a master row) at an integer x, each x evaluated
        once, and whether x is better than any before it (it becomes ``best``)."""
        key = x.astype(np.int8).tobytes()
        known = self.evaluated.get(key)
        if known is not None:
            return *known, False
        t0 = time.perf_counter()
        try:
            values, grads = self.pool.evaluate(x)
        except SolveError:  # a first stage some master row forbids (a heuristic's candidate): no schedule
            values, grads = np.full(len(self.theta), np.inf), None
        self.evaluation_s += time.perf_counter() - t0
        self.evaluated[key] = values, grads
        value = self.master.expected_cost(x, values)
        if value < self.value:
            self.best, self.value = x.copy(), value
            return values, grads, True
        return values, grads, False

    def offer(self, sol, x: np.ndarray, values: np.ndarray) -> None:
        """Hand SCIP the candidate ``sol`` with theta_s = Q_s(x): feasible (every cut under-estimates Q_s, and the
        master's relaxation holds at sol's own values), so SCIP's primal bound is the best schedule's."""
        m = self.model
        offered = m.createOrigSol(None)
        for var in self.columns:
            m.setSolVal(offered, var, m.getSolVal(sol, var))
        for var, xj in zip(self.x, x):
            m.setSolVal(offered, var, float(xj))
        for var, q in zip(self.theta, values):
            m.setSolVal(offered, var, float(q))
        m.trySol(offered)


def _handler_class(scip):
    """The constraint handler class, made once PySCIPOpt is imported (it subclasses its ``Conshdlr``)."""
    result = scip.SCIP_RESULT

    class Scenarios(scip.Conshdlr):
        """theta_s >= Q_s(x) for every scenario s, at integer candidates: checked, and enforced with cuts."""

        def __init__(self, tree: _Tree):
            super().__init__()
            self.tree = tree
            self.transformed = None  # SCIP's transformed variables (x, theta), for the rows of cuts

        def _candidate(self, sol):
            t, m = self.tree, self.tree.model
            x = np.rint([m.getSolVal(sol, v) for v in t.x])
            theta = np.array([m.getSolVal(sol, v) for v in t.theta])
            values, grads, better = t.recourse(x)
            violated = theta < values - _TOLERANCE * (1 + np.abs(values))
            if better and violated.any():
                t.offer(sol, x, values)
            return x, values, grads, violated

        def conscheck(self, constraints, solution, checkintegrality, checklprows, printreason, completely):
            t = self.tree
            if t.model.getSolObjVal(solution) > t.value + _TOLERANCE * (1 + abs(t.value)):
                return {"result": result.INFEASIBLE}  # worse than the best, whatever its recourse
            *_, violated = self._candidate(solution)
            return {"result": result.INFEASIBLE if violated.any() else result.FEASIBLE}

        def consenfolp(self, constraints, nusefulconss, solinfeasible):
            if solinfeasible:  # a fractional LP solution: branching comes first
                return {"result": result.FEASIBLE}
            x, values, grads, violated = self._candidate(None)
            if not violated.any():
                return {"result": result.FEASIBLE}
            if grads is None:
                return {"result": result.CUTOFF}
            self._cut(x, values, grads, violated)
            return {"result": result.SEPARATED}

        def consenfops(self, constraints, nusefulconss, solinfeasible, objinfeasible):
            if solinfeasible:
                return {"result": result.FEASIBLE}
            *_, violated = self._candidate(None)
            return {"result": result.INFEASIBLE if violated.any() else result.FEASIBLE}

        def conslock(self, constraint, locktype, nlockspos, nlocksneg):
            m = self.tree.model
            for v in self.tree.x:  # theta_s - g_s x >= rhs: x may move either way
                m.addVarLocks(v, nlockspos + nlocksneg, nlockspos + nlocksneg)
            for v in self.tree.theta:  # theta only down
                m.addVarLocks(v, nlockspos, nlocksneg)

        def _cut(self, x, values, grads, violated) -> None:
            t, m = self.tree, self.tree.model
            if self.transformed is None:
                self.transformed = ([m.getTransformedVar(v) for v in t.x], [m.getTransformedVar(v) for v in t.theta])
            xs, thetas = self.transformed
            for s in np.flatnonzero(violated):
                row = m.createEmptyRowUnspec(name=f"benders_{s}", lhs=float(values[s]) - exact.dot(grads[s], x), rhs=None,
                                             local=False)
                m.cacheRowExtensions(row)
                m.addVarToRow(row, thetas[s], 1.0)
                for j in np.flatnonzero(grads[s]):
                    m.addVarToRow(row, xs[j], float(-grads[s][j]))
                m.flushRowExtensions(row)
                m.addPoolCut(row)
                m.addCut(row, forcecut=True)

    return Scenarios
