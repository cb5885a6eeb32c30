"""Compile a cvxpy problem once and drive it in HiGHS directly: change bounds, re-solve warm, read duals.

cvxpy builds the model (one code path for every solver route); highspy then keeps each compiled LP alive, so a
decomposition changes a few column bounds and re-solves from the last basis instead of recompiling.
"""

from __future__ import annotations

from dataclasses import dataclass

import cvxpy as cp
import highspy
import numpy as np

INF = highspy.kHighsInf
# HiGHS reports a feasible incumbent with primal_solution_status 2 (kSolutionStatusFeasible).
FEASIBLE = 2
# The threads of every HiGHS solve: left at 0, HiGHS searches with as many workers as the process has cores, and the
# tree it searches depends on them, so a search would take another path on another machine
# (docs/notes/2026-12-08-highs-one-thread.md). The count is HiGHS's per OS thread, not per model, so every HiGHS we
# make is given this one (docs/solver.md, "The same path on every machine").
HIGHS_THREADS = 1


@dataclass(frozen=True)
class Columns:
    """Where each cvxpy variable's entries sit among the compiled columns (cvxpy flattens column-major)."""

    offsets: dict[int, int]

    def holds(self, var: cp.Variable) -> bool:
        """Whether ``var`` takes part in the problem (cvxpy compiles only the variables it meets)."""
        return var.id in self.offsets

    def of(self, var: cp.Variable) -> np.ndarray:
        return np.arange(self.offsets[var.id], self.offsets[var.id] + var.size, dtype=np.int32)

    def shaped(self, var: cp.Variable) -> np.ndarray:
        """``var``'s columns in its own shape."""
        return self.of(var).reshape(var.shape, order="F")

    def value(self, var: cp.Variable, x: np.ndarray) -> np.ndarray:
        return np.asarray(x)[self.shaped(var)]


def compile_problem(problem: cp.Problem) -> tuple[dict, Columns]:
    """The HiGHS-ready data of ``problem`` at its current parameter values, and its column map.

    With parameters (DPP), repeated calls only re-apply the parameters: about 2 ms for one scenario here.
    """
    data, _, inverse = problem.get_problem_data(cp.HIGHS, canon_backend="SCIPY")
    offsets = next(d.var_offsets for d in reversed(inverse) if hasattr(d, "var_offsets"))
    return data, Columns(dict(offsets))


def forked() -> None:
    """In a process just forked from one that has solved with HiGHS: let HiGHS start its threads anew. Its scheduler
    is one for the whole process, and its worker threads are not forked with it: a MIP whose tasks wait for them
    waits for ever (a schedule solved in a worker of dmosim/launch/solves.py did, spinning, once the market's process
    had solved the agents' bids)."""
    highspy.Highs.resetGlobalScheduler(False)  # not blocking: there is no thread to join


def highs_model(data: dict, integer: bool = True) -> highspy.Highs:
    """A HiGHS instance holding cvxpy's conic data: rows A x = b (zero cone) then A x <= b (nonneg cone)."""
    A = data["A"].tocsc()
    m, n = A.shape
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = n, m
    lp.col_cost_ = np.asarray(data["c"], float)
    lp.col_lower_, lp.col_upper_ = column_bounds(data)
    lp.row_lower_, lp.row_upper_ = row_bounds(data)
    lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
    lp.a_matrix_.start_, lp.a_matrix_.index_, lp.a_matrix_.value_ = A.indptr, A.indices, A.data
    binaries = list(data["bool_vars_idx"]) + list(data["int_vars_idx"])
    if integer and binaries:
        kinds = [highspy.HighsVarType.kContinuous] * n
        for j in binaries:
            kinds[j] = highspy.HighsVarType.kInteger
        lp.integrality_ = kinds
        lower, upper = np.array(lp.col_lower_), np.array(lp.col_upper_)
        lower[binaries], upper[binaries] = np.maximum(lower[binaries], 0), np.minimum(upper[binaries], 1)
        lp.col_lower_, lp.col_upper_ = lower, upper
    h = highspy.Highs()
    h.setOptionValue("output_flag", False)
    h.setOptionValue("threads", HIGHS_THREADS)
    h.passModel(lp)
    return h


def work(info: highspy.HighsInfo) -> tuple[int, int]:
    """The simplex iterations and branch-and-bound nodes of the HiGHS solve whose ``info`` this is: the same on every
    machine, where its seconds are not. A MIP's simplex iterations are every LP iteration of its tree (the nodes',
    strong branching's, separation's and its heuristics' LPs); an LP has no nodes (HiGHS says -1)."""
    return max(int(info.simplex_iteration_count), 0), max(int(info.mip_node_count), 0)


def column_bounds(data: dict) -> tuple[np.ndarray, np.ndarray]:
    """The columns' lower and upper bounds in cvxpy's data (infinite where it gives none)."""
    n = data["A"].shape[1]
    lb, ub = data["lower_bounds"], data["upper_bounds"]
    return (np.full(n, -INF) if lb is None else np.asarray(lb, float),
            np.full(n, INF) if ub is None else np.asarray(ub, float))


def row_bounds(data: dict) -> tuple[np.ndarray, np.ndarray]:
    """The rows' lower and upper bounds: cvxpy's equalities (its zero cone) first, then its A x <= b."""
    b, zero = np.asarray(data["b"], float), data["dims"].zero
    return np.concatenate([b[:zero], np.full(len(b) - zero, -INF)]), b


def fix_columns(h: highspy.Highs, cols: np.ndarray, values: np.ndarray) -> None:
    values = np.asarray(values, float)
    h.changeColsBounds(len(cols), cols, values, values)
