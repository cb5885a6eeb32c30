"""Multi-cut Benders (L-shaped) decomposition of the stochastic schedule: the fast, certified path.

First stage x = (I, y, w, u, v, z): hourly binaries of units, start-ups/shut-downs, storage modes and loads.
Given x, each scenario is an LP (objective (1) without start-up costs, constraints (2)-(5), (8)-(9), (11)-(12),
(15)-(16), (18)-(21)); curtailment and spill make it feasible for every x the master allows, because the master
carries the scenario-independent storage and load constraints itself (inside its relaxation). The scenario LPs
are compiled once from the same cvxpy model as the extensive form (scenario data as Parameters: scenario_lp.py),
kept alive in HiGHS, and re-solved warm as x changes: their optimal value Q_s(x) is convex in x and the reduced costs of the
fixed x columns are a subgradient, so theta_s >= Q_s(x^) + g_s (x - x^) is a valid cut. The master (first stage, an hourly Jensen
relaxation of the second stage (relaxation.py), and theta per scenario) is first solved as an LP until its cuts
describe the LP relaxation, then, with the cuts slack there set aside, as a MILP.
The master's MIP dual bound is a valid lower bound; every integer x^ evaluated on all scenarios is an upper
bound. docs/solver.md gives the design and the measurements.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import multiprocessing as mp
import os
import signal
import sys
import time
from dataclasses import dataclass, field

import cvxpy as cp
import highspy
import numpy as np

from scenarios import exact
from scenarios.case import Case
from scenarios.generation import ScenarioSet
from scenarios.horizon import HOURS

from ..model import (FIRST_STAGE, Params, dp_plus_of, first_stage_constraints, first_stage_variables, startup_cost,
                     variables)
from ..schedule import CostBreakdown, Dispatch, FirstStage, StochasticSchedule, Timings
from .extensive import SolveError
from .highs import FEASIBLE, HIGHS_THREADS, INF, compile_problem, fix_columns, highs_model, work
from .relaxation import group_relaxation, islanding_groups, relaxed
from .scenario_lp import ScenarioLP


class Subproblems:
    """The scenario LPs of a subset of scenarios, each a live HiGHS model (warm re-solves); ``simplex_iterations``:
    those of every solve so far."""

    def __init__(self, case: Case, scen: ScenarioSet, params: Params, indices):
        self.lp = ScenarioLP(case, params, scen.subperiods, scen.N)
        self.indices = list(indices)
        self.models: dict[int, highspy.Highs] = {}
        self.simplex_iterations = 0
        for s in self.indices:
            data, self.columns = self.lp.compile(scen, s)
            self.models[s] = highs_model(data, integer=False)
        self.x_held, self.x_cols = self.lp.first_stage(self.columns)

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Q_s(x) and a subgradient per scenario of this subset."""
        values, grads = np.empty(len(self.indices)), np.zeros((len(self.indices), len(self.x_held)))
        for i, s in enumerate(self.indices):
            h = self._solve(s, x)
            values[i] = h.getInfo().objective_function_value
            grads[i, self.x_held] = np.asarray(h.getSolution().col_dual)[self.x_cols]
        return values, grads

    def dispatch(self, x: np.ndarray) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """Second-stage values (name -> (subset, *shape)) and cost terms (name -> (subset,)) at x."""
        read = [self.lp.read(self.columns, np.asarray(self._solve(s, x).getSolution().col_value))
                for s in self.indices]
        return ({n: np.array([a[n] for a, _ in read]) for n in read[0][0]},
                {n: np.array([c[n] for _, c in read]) for n in read[0][1]})

    def _solve(self, s: int, x: np.ndarray) -> highspy.Highs:
        h = self.models[s]
        fix_columns(h, self.x_cols, np.asarray(x)[self.x_held])
        h.run()
        self.simplex_iterations += work(h.getInfo())[0]
        if h.getModelStatus() != highspy.HighsModelStatus.kOptimal:
            raise SolveError(f"scenario {s}: subproblem {h.modelStatusToString(h.getModelStatus())} for the "
                             "master's first stage (complete recourse violated: check the case)")
        return h


PR_SET_PDEATHSIG = 1  # prctl(2): the signal the kernel sends a process when its parent dies (linux/prctl.h)


def _worker(conn, case, scen, params, indices, solver: int) -> None:
    dies_with(solver)
    sub = Subproblems(case, scen, params, indices)
    conn.send("ready")
    while True:
        command, x = conn.recv()
        if command == "stop":
            return
        try:
            conn.send(("ok", sub.evaluate(x) if command == "evaluate" else sub.dispatch(x), sub.simplex_iterations))
        except Exception as exc:  # the parent re-raises it; the worker stays usable
            conn.send(("error", exc, sub.simplex_iterations))


def dies_with(solver: int) -> None:
    """Have the kernel SIGKILL this worker when the process that solves (``solver``, its parent) dies, however it dies
    (SIGTERM to ``dmosim solve`` or a benchmark, SIGKILL): the worker waits on a pipe whose other end it holds itself
    (forked), so it never sees that end close, and would wait for ever. A subproblems' worker here, a schedule's in a
    market in one process (dmosim/launch/solves.py). Linux only (``PR_SET_PDEATHSIG``); elsewhere, nothing."""
    if not sys.platform.startswith("linux"):
        return
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != solver:  # it died before the line above: no signal will come
        os._exit(1)


class ScenarioPool:
    """Subproblems spread over ``workers`` processes (fork), or kept in this process when workers == 1."""

    def __init__(self, case: Case, scen: ScenarioSet, params: Params, workers: int):
        self.S = scen.S
        parts = [list(range(w, scen.S, workers)) for w in range(min(workers, scen.S))]
        self.parts = parts
        self._counted = [0] * len(parts)  # each worker's simplex iterations, as its last reply said
        if len(parts) == 1:
            self.local, self.procs = Subproblems(case, scen, params, parts[0]), []
            return
        self.local = None
        ctx = mp.get_context("fork")
        self.conns, self.procs = [], []
        for part in parts:
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(child, case, scen, params, part, os.getpid()), daemon=True)
            proc.start()
            self.conns.append(parent)
            self.procs.append(proc)
        for conn in self.conns:
            conn.recv()

    def _map(self, command: str, x: np.ndarray) -> list:
        if self.local is not None:
            return [self.local.evaluate(x) if command == "evaluate" else self.local.dispatch(x)]
        for conn in self.conns:
            conn.send((command, x))
        replies = [conn.recv() for conn in self.conns]
        self._counted = [counted for _, _, counted in replies]
        for status, payload, _ in replies:
            if status == "error":
                raise payload
        return [payload for _, payload, _ in replies]

    @property
    def simplex_iterations(self) -> int:
        """The simplex iterations of every scenario LP solved so far, in every worker."""
        return self.local.simplex_iterations if self.local is not None else sum(self._counted)

    def evaluate(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        values, grads = np.empty(self.S), None
        for part, (v, g) in zip(self.parts, self._map("evaluate", x)):
            values[part] = v
            grads = np.empty((self.S, g.shape[1])) if grads is None else grads
            grads[part] = g
        return values, grads

    def dispatch(self, x: np.ndarray):
        arrays, costs = {}, {}
        for part, (a, c) in zip(self.parts, self._map("dispatch", x)):
            for name, value in a.items():
                arrays.setdefault(name, np.empty((self.S, *value.shape[1:])))[part] = value
            for name, value in c.items():
                costs.setdefault(name, np.empty(self.S))[part] = value
        return arrays, costs

    def close(self) -> None:
        for conn in getattr(self, "conns", []):
            conn.send(("stop", None))
        for proc in self.procs:
            proc.join(timeout=5)
            if proc.is_alive():
                proc.kill()


_SLACK = 1e-6  # relative slack above which a cut counts as not binding
_EARLY_GAP = 0.02  # relative gap of the first MILP masters
_CUTOFF_MARGIN = 1e-6  # relative: how far a master's pruning may trust a bound at its cutoff
# A search stalls when STALL_MASTERS integer masters in a row find no better schedule and raise the bound by less
# than STALL_RISE x the target gap in all; it then goes on with one relaxation group per islanding pattern
# (``Master.regrouped``; docs/notes/2026-11-28-stalled-search-regroup.md).
STALL_MASTERS = 10
STALL_RISE = 0.1


class CutPool:
    """Every cut found so far, theta_s - g x >= rhs, whether or not the master currently carries it."""

    def __init__(self, nx: int):
        self.scenario = np.zeros(0, dtype=np.int64)
        self.rhs = np.zeros(0)
        self.grads = np.zeros((0, nx))

    @property
    def size(self) -> int:
        return len(self.rhs)

    def add(self, scenario: np.ndarray, rhs: np.ndarray, grads: np.ndarray) -> None:
        self.scenario = np.concatenate([self.scenario, scenario])
        self.rhs = np.concatenate([self.rhs, rhs])
        self.grads = np.vstack([self.grads, grads])

    def slack(self, ids: np.ndarray, x: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """theta_s - g x - rhs of cuts ``ids`` at (x, theta): negative where a cut is violated."""
        return theta[self.scenario[ids]] - exact.matvec(self.grads[ids], x) - self.rhs[ids]


class Master:
    """First stage, the groups' hourly relaxation (relaxation.py) linked to theta_s, and theta_s >= cuts."""

    def __init__(self, case: Case, scen: ScenarioSet, params: Params, label: np.ndarray | None = None):
        # The groups' hourly relaxation (relaxation.py) also carries the scenario-independent storage and load
        # constraints, so every x the master allows has a feasible dispatch in every scenario. One group (all
        # scenarios) by default: finer groups (by islanding pattern) made each MILP master several times slower
        # for no better final bound (docs/solver.md).
        label = np.zeros(scen.S, dtype=int) if label is None else label
        v = variables(case, int(label.max()) + 1, HOURS, params=relaxed(params))
        theta = cp.Variable(scen.S, nonneg=True)  # Q_s >= 0: every cost term is non-negative
        relaxation = group_relaxation(case, scen, params, v, label)
        cons = (first_stage_constraints(case, v, 1.0 / scen.subperiods) + relaxation.constraints
                + [relaxation.linking(theta)])
        problem = cp.Problem(cp.Minimize(startup_cost(case, v) + scen.probability @ theta), cons)
        data, columns = compile_problem(problem)
        self.h = highs_model(data, integer=True)
        self.var, self.probability = v, scen.probability
        self.x_cols = np.concatenate([columns.of(v[n]) for n in FIRST_STAGE if n in v])
        self.theta_cols = columns.of(theta)
        self.cost = np.asarray(data["c"], float)[self.x_cols]  # start-up and shut-down costs of x
        self.binary = np.asarray(data["bool_vars_idx"], dtype=np.int32)
        self.base_rows = self.h.getNumRow()
        self.pool = CutPool(len(self.x_cols))
        self.active = np.zeros(0, dtype=np.int64)  # pool ids of the cut rows, in master row order
        self.incumbent = None
        self.last = None
        self.work = (0, 0)  # the simplex iterations and nodes of the last solve (``highs.work``)

    def first_stage_cost(self, x: np.ndarray) -> float:
        return exact.dot(self.cost, x)

    def expected_cost(self, x: np.ndarray, values: np.ndarray) -> float:
        """Objective (1) of first stage ``x`` whose scenario recourse costs are ``values``: an upper bound."""
        return self.first_stage_cost(x) + exact.dot(self.probability, values)

    def cut_at(self, pool: ScenarioPool, x: np.ndarray) -> tuple[np.ndarray, float, float, int]:
        """Evaluate ``x`` on the scenario LPs and add its cuts: Q_s(x), the expected cost, the seconds and the simplex
        iterations it took."""
        t0, before = time.perf_counter(), pool.simplex_iterations
        values, grads = pool.evaluate(x)
        self.add_cuts(x, values, grads)
        return values, self.expected_cost(x, values), time.perf_counter() - t0, pool.simplex_iterations - before

    def add_cuts(self, x: np.ndarray, values: np.ndarray, grads: np.ndarray) -> None:
        """theta_s - g_s x >= Q_s(x^) - g_s x^ for every scenario s: into the pool, and active in the master."""
        self.pool.add(np.arange(len(values)), values - exact.matvec(grads, x), grads)
        self._activate(np.arange(self.pool.size - len(values), self.pool.size))

    def _activate(self, ids: np.ndarray) -> None:
        """Append pool cuts ``ids`` as master rows (zero coefficients dropped)."""
        if len(ids) == 0:
            return
        scenario, rhs, grads = self.pool.scenario[ids], self.pool.rhs[ids], self.pool.grads[ids]
        n, nx = grads.shape
        index = np.column_stack([self.theta_cols[scenario][:, None], np.broadcast_to(self.x_cols, (n, nx))])
        coef = np.column_stack([np.ones(n), -grads])
        keep = coef != 0
        starts = np.concatenate([[0], np.cumsum(keep.sum(axis=1))[:-1]]).astype(np.int32)
        self.h.addRows(n, rhs, np.full(n, INF), int(keep.sum()), starts, index[keep].astype(np.int32), coef[keep])
        self.active = np.concatenate([self.active, ids])

    def prune(self) -> None:
        """Drop the active cuts that are slack at the last master solution; they stay in the pool.

        Dense cuts make each MILP master's root slow (presolve, separation): keeping only the binding ones
        made a 10-scenario master about 8 times faster. A master with fewer cuts is a relaxation, so its bound
        stays valid. Called once, when the LP phase ends: its cuts at fractional points are mostly slack for
        the integer phase, while every cut at an integer x^ stays, so a repeated x^ cannot cycle.
        """
        slack = self.pool.slack(self.active, self.last[self.x_cols], self.last[self.theta_cols])
        drop = np.flatnonzero(slack > _SLACK * (1 + np.abs(self.pool.rhs[self.active])))
        self.h.deleteRows(len(drop), (self.base_rows + drop).astype(np.int32))
        self.active = np.delete(self.active, drop)

    def solve(self, relaxed: bool, gap: float, time_limit: float | None,
              cutoff: float | None = None) -> tuple[np.ndarray | None, float, float]:
        """x^, the master's objective and its lower bound (for an LP, the two are equal).

        With ``cutoff``, a MILP master looks only for x below it: one whose every x costs at least the cutoff
        returns None and the cutoff as its bound (HiGHS's ``objective_bound`` prunes the nodes above it, so the
        master stops as soon as its bound passes the cutoff instead of closing its own gap)."""
        kind = highspy.HighsVarType.kContinuous if relaxed else highspy.HighsVarType.kInteger
        self.h.changeColsIntegrality(len(self.binary), self.binary, np.array([kind] * len(self.binary)))
        self.h.setOptionValue("mip_rel_gap", gap)
        self.h.setOptionValue("time_limit", float(time_limit) if time_limit else INF)
        self.h.setOptionValue("objective_bound", INF if relaxed or cutoff is None else float(cutoff))
        if not relaxed and self.incumbent is not None:
            self.h.setSolution(self._start())
        self.h.run()
        info, status = self.h.getInfo(), self.h.getModelStatus()
        self.work = work(info)
        # Nothing below the cutoff: HiGHS says infeasible, or, started from an incumbent above it, returns that
        # incumbent as optimal with its value as the bound; either way the master's optimum is at the cutoff or above.
        if not relaxed and cutoff is not None and (status == highspy.HighsModelStatus.kInfeasible or (
                status == highspy.HighsModelStatus.kOptimal and info.objective_function_value >= cutoff)):
            return None, cutoff, cutoff
        if info.primal_solution_status != FEASIBLE:
            raise SolveError(f"master: no solution ({self.h.modelStatusToString(self.h.getModelStatus())})")
        self.last = np.asarray(self.h.getSolution().col_value)
        x = self.last[self.x_cols]
        objective = info.objective_function_value
        bound = objective if relaxed else info.mip_dual_bound
        return (x if relaxed else np.rint(x)), objective, bound

    def completion(self, x: np.ndarray) -> np.ndarray | None:
        """The master's columns at first stage ``x`` (every other column at its LP optimum given ``x``), or None if
        ``x`` breaks one of the master's first-stage constraints: a start from elsewhere (another day's first stage)
        made a MILP start the master's own solutions are."""
        lp = self.h.getLp()
        lower, upper = np.asarray(lp.col_lower_)[self.x_cols], np.asarray(lp.col_upper_)[self.x_cols]
        kind = highspy.HighsVarType.kContinuous
        self.h.changeColsIntegrality(len(self.binary), self.binary, np.array([kind] * len(self.binary)))
        fix_columns(self.h, self.x_cols, x)
        self.h.setOptionValue("objective_bound", INF)
        self.h.run()
        self.work = work(self.h.getInfo())
        ok = self.h.getModelStatus() == highspy.HighsModelStatus.kOptimal
        col = np.asarray(self.h.getSolution().col_value) if ok else None
        self.h.changeColsBounds(len(self.x_cols), self.x_cols, lower, upper)
        return col

    def remember(self, x: np.ndarray, values: np.ndarray, col: np.ndarray | None = None) -> None:
        """The best integer x so far and its scenario costs: the next MILP starts from it (its columns ``col``, by
        default the last master solution's)."""
        self.incumbent = ((self.last if col is None else col).copy(), x, values)

    def regrouped(self, case: Case, scen: ScenarioSet, params: Params, label: np.ndarray) -> Master:
        """The same search with the relaxation's groups ``label``: a new master sharing this one's cut pool, carrying
        the cuts this one carries, and started from its incumbent. Finer groups under-estimate the recourse at
        least as closely (Jensen within each group), so its bound is at least this one's at every x."""
        other = Master(case, scen, params, label)
        other.pool = self.pool
        other._activate(self.active)
        if self.incumbent is not None:
            _, x, values = self.incumbent
            col = other.completion(x)  # x meets the same first-stage constraints: None only if HiGHS fails
            if col is not None:
                other.remember(x, values, col)
        return other

    def _start(self) -> highspy.HighsSolution:
        # theta_s = Q_s(x) satisfies every cut at x (cuts under-estimate Q_s), so this start is feasible.
        col, x, values = self.incumbent
        col = col.copy()
        col[self.x_cols], col[self.theta_cols] = x, values
        start = highspy.HighsSolution()
        start.col_value = col
        start.value_valid = True
        return start


@dataclass(frozen=True)
class Found:
    """Where the search ended: the best first stage by variable name (``first_stage_values``) and its start-up and
    shut-down cost, its dispatch in every scenario (``arrays``: variable -> (S, ...); ``costs``: term -> (S,)), the
    certified lower bound and the status (``optimal`` or ``time_limit``)."""

    first: dict[str, np.ndarray]
    startup: float
    arrays: dict[str, np.ndarray]
    costs: dict[str, np.ndarray]
    lower: float
    status: str


ITERATIONS = ("lp", "milp", "tree")  # the trace's phases that are iterations: a master solved


WORK = ("master_simplex_iterations", "master_nodes", "subproblems_simplex_iterations")  # a trace row's work


@dataclass
class Trace:
    """Where the time and the work went: per row the phase, the lower and upper bounds, the master's seconds,
    simplex iterations and nodes, and the subproblems' seconds and simplex iterations (they are LPs: no nodes). A row
    is an iteration (``lp``, ``milp``, ``tree``), a start evaluated between them (``start``, ``start_set_aside``: the
    master's work is the LP that completes the start), or a stalled search's new master (``regroup``, its seconds to
    build as the master's, and its work the LP that completes the incumbent in it); the last three solve no master
    and are not counted in ``iterations``."""

    rows: list = field(default_factory=list)
    build_s: float = 0.0

    def add(self, phase, lb, ub, master_s, sub_s, master_work: tuple[int, int] = (0, 0), sub_iterations: int = 0):
        self.rows.append({"phase": phase, "lower_bound": lb, "upper_bound": ub, "master_s": master_s,
                          "subproblems_s": sub_s, "master_simplex_iterations": master_work[0],
                          "master_nodes": master_work[1], "subproblems_simplex_iterations": sub_iterations})

    def summary(self) -> dict:
        master = sum(r["master_s"] for r in self.rows)
        sub = sum(r["subproblems_s"] for r in self.rows)
        return {"iterations": sum(r["phase"] in ITERATIONS for r in self.rows),
                "lp_iterations": sum(r["phase"] == "lp" for r in self.rows),
                "build_s": self.build_s, "master_s": master, "subproblems_s": sub,
                **{k: sum(r[k] for r in self.rows) for k in WORK}}


class Stall:
    """Whether the integer masters have stalled (``STALL_MASTERS`` in a row without a better schedule, the bound
    raised by less than ``STALL_RISE`` x ``gap`` of the best value): said once, then never again in the solve."""

    def __init__(self, gap: float):
        self.gap, self.said = gap, False
        self.bounds = collections.deque(maxlen=STALL_MASTERS + 1)  # (lower, upper) after each of the last masters

    def after(self, lower: float, upper: float) -> None:
        """An integer master's bounds, as the search stands after it."""
        self.bounds.append((lower, upper))

    def stalled(self) -> bool:
        if self.said or len(self.bounds) <= STALL_MASTERS:
            return False
        (lower0, upper0), (lower, upper) = self.bounds[0], self.bounds[-1]
        self.said = upper >= upper0 and lower - lower0 < STALL_RISE * self.gap * abs(upper)
        return self.said


def solve_decomposed(case: Case, scen: ScenarioSet, params: Params, *, gap: float = 0.005,
                     time_limit: float | None = None, workers: int = 2, lp_tolerance: float = 1e-3,
                     max_lp_iterations: int = 100, stability: float = 0.5, progress=None,
                     start: FirstStage | None = None) -> StochasticSchedule:
    """Benders decomposition to a certified relative gap; returns the same StochasticSchedule as the extensive form.
    ``start``: a first stage (another schedule's, e.g. the day before's), evaluated once the LP phase ends: if the
    master's first-stage constraints allow it, it is the first incumbent (an upper bound, the first MILP master's
    cutoff and its start). A search whose integer masters stall goes on with one relaxation group per islanding
    pattern (``Stall``, ``Master.regrouped``)."""
    began = time.perf_counter()
    deadline = began + time_limit if time_limit else None
    with decomposition(case, scen, params, workers) as (master, pool, trace):
        report = reporter(progress, trace, began)
        relax(master, pool, trace, deadline, report, gap=gap, lp_tolerance=lp_tolerance,
              max_lp_iterations=max_lp_iterations, stability=stability)
        lower, upper, best = -np.inf, np.inf, None
        if start is not None:
            upper, best = begin_from(master, pool, trace, first_stage_vector(case, first_stage_variables(start)))
            report("start after iteration", trace.rows[-1]["lower_bound"], upper, 0.0)

        def master_solve():
            # Early MILP masters only steer the search: solve them to a fraction of the current gap, and to
            # half the target gap once close, where their bound is the one certified. A MILP master need not
            # prove more than the target: x costing (1 - gap) x the best value or more are cut off
            # (``_CUTOFF_MARGIN`` above it, so that a bound at the cutoff, less HiGHS's tolerance, certifies).
            t0 = time.perf_counter()
            remaining = None if deadline is None else max(1.0, deadline - t0)
            master_gap = max(gap / 2, min(_EARLY_GAP, apart(lower, upper) / 4))
            cutoff = upper - (gap - 2 * _CUTOFF_MARGIN) * abs(upper) if np.isfinite(upper) else None
            x, _, bound = master.solve(relaxed=False, gap=master_gap, time_limit=remaining, cutoff=cutoff)
            if x is None:  # nothing below the cutoff: the bound is the cutoff, less the pruning tolerance
                bound -= _CUTOFF_MARGIN * abs(upper)
            return x, bound, time.perf_counter() - t0

        status = "optimal"
        stall = Stall(gap)
        while True:
            if stall.stalled():
                t0 = time.perf_counter()
                master = master.regrouped(case, scen, params, islanding_groups(scen))
                built_s = time.perf_counter() - t0
                trace.add("regroup", lower, upper, built_s, 0.0, master.work)
                report("stalled: one relaxation group per islanding pattern after iteration", lower, upper, built_s)
            x, bound, master_s = master_solve()
            lower = max(lower, bound)
            if x is None:  # every x left costs (1 - gap) x the best value or more: the best is certified
                trace.add("milp", bound, upper, master_s, 0.0, master.work)
                report("integer master, iteration", lower, upper, master_s)
                break
            values, value, sub_s, sub_iterations = master.cut_at(pool, x)
            trace.add("milp", bound, value, master_s, sub_s, master.work, sub_iterations)
            if value < upper:
                upper, best = value, x
                master.remember(x, values)
            report("integer master, iteration", lower, upper, master_s)
            if apart(lower, upper) <= gap:
                break
            stall.after(lower, upper)
            if late(deadline):
                status = "time_limit"
                break
        arrays, costs = pool.dispatch(best)
    found = Found(first_stage_values(master.var, best), master.first_stage_cost(best), arrays, costs, lower, status)
    return schedule_of(case, scen, params, found, trace, time.perf_counter() - began, "benders")


def begin_from(master: Master, pool: ScenarioPool, trace: Trace, x: np.ndarray) -> tuple[float, np.ndarray | None]:
    """A first stage from elsewhere as the search's first incumbent: (its expected cost, x) if the master's
    first-stage constraints allow it, else (inf, None) and nothing changes. Its cuts go in either way (valid at any
    x). The trace gets a row ``start`` with the start's value as its upper bound, or ``start_set_aside`` with the
    LP phase's last bounds."""
    bound = trace.rows[-1]["lower_bound"]
    col = master.completion(x)
    if col is None:
        trace.add("start_set_aside", bound, trace.rows[-1]["upper_bound"], 0.0, 0.0, master.work)
        return np.inf, None
    values, value, sub_s, sub_iterations = master.cut_at(pool, x)
    master.remember(x, values, col)
    trace.add("start", bound, value, 0.0, sub_s, master.work, sub_iterations)
    return value, x


@contextlib.contextmanager
def decomposition(case: Case, scen: ScenarioSet, params: Params, workers: int):
    """The master, the scenario pool on ``workers`` processes and the trace of one decomposed solve; the pool's
    processes stop on leaving. The trace's build time counts building, and starting and stopping the pool."""
    start = time.perf_counter()
    pool = ScenarioPool(case, scen, params, workers)
    trace = Trace()
    try:
        master = Master(case, scen, params)
        trace.build_s = time.perf_counter() - start
        yield master, pool, trace
    finally:
        stop = time.perf_counter()
        pool.close()
        trace.build_s += time.perf_counter() - stop


def reporter(progress, trace: Trace, start: float):
    """report(what, lower, upper, master_s): a progress line per iteration of a decomposed solve, if ``progress``."""

    def report(what: str, lb: float, ub: float, master_s: float) -> None:
        if progress:
            progress(f"benders {what} {trace.summary()['iterations']}: bound {lb:,.2f}, best {ub:,.2f} "
                     f"({apart(lb, ub):.2%} apart), master {master_s:.1f} s, "
                     f"{time.perf_counter() - start:.0f} s in all")

    return report


def relax(master: Master, pool: ScenarioPool, trace: Trace, deadline: float | None, report, *, gap: float,
          lp_tolerance: float = 1e-3, max_lp_iterations: int = 100, stability: float = 0.5) -> None:
    """The LP relaxation of the master first: cheap masters, most of the cuts; then the cuts slack at its optimum set
    aside (``Master.prune``). In-out stabilisation (Ben-Ameur and Neto 2007): cuts are taken between the master's
    point and the best point so far, which damps Kelley's zig-zag; the LP bound is the master's, the value at any point
    an upper bound of the LP relaxation. Stops within ``lp_tolerance`` of the LP relaxation's optimum."""
    core, core_value = None, np.inf
    for _ in range(max_lp_iterations):
        t0 = time.perf_counter()
        x_master, _, bound = master.solve(relaxed=True, gap=gap, time_limit=None)
        master_s = time.perf_counter() - t0
        x = x_master if core is None else stability * x_master + (1 - stability) * core
        _, value, sub_s, sub_iterations = master.cut_at(pool, x)
        trace.add("lp", bound, value, master_s, sub_s, master.work, sub_iterations)
        if value < core_value:
            core, core_value = x, value
        report("LP relaxation, iteration", bound, core_value, master_s)
        if apart(bound, core_value) <= lp_tolerance or late(deadline):
            break
    master.prune()


def first_stage_vector(case: Case, values: dict[str, np.ndarray]) -> np.ndarray:
    """A first stage by variable name as the flat x of the master and the subproblems (``first_stage_values``
    reads it back)."""
    var = variables(case, 1, HOURS)
    return np.concatenate([np.asarray(values[n], float).reshape(var[n].shape).ravel(order="F")
                           for n in FIRST_STAGE if n in var])


def first_stage_values(var: dict[str, cp.Variable], x: np.ndarray) -> dict[str, np.ndarray]:
    """The flat first stage x (names in FIRST_STAGE order, each flattened column-major) by variable name."""
    pieces, offset = {}, 0
    for name in FIRST_STAGE:
        if name in var:
            pieces[name] = x[offset:offset + var[name].size].reshape(var[name].shape, order="F")
            offset += var[name].size
    return pieces


def apart(lower: float, upper: float) -> float:
    """The relative gap (upper - lower) / |upper|; infinite until there is an upper bound. A schedule that costs
    nothing (a microgrid importing free energy) is closed once the bound reaches it."""
    if not np.isfinite(upper):
        return np.inf
    if upper == 0:
        return 0.0 if lower >= upper else np.inf
    return (upper - lower) / abs(upper)


def late(deadline: float | None) -> bool:
    return deadline is not None and time.perf_counter() >= deadline


def _dispatch(case: Case, scen: ScenarioSet, params: Params, arrays: dict[str, np.ndarray]) -> Dispatch:
    """The subproblems' second-stage values (variable -> (S, ...)) as the schedule's dispatch."""
    G, R, Dn, S, N = len(case.units), len(case.renewables), len(case.loads), scen.S, scen.N

    def stacked(name, rows):  # (S, rows, N) per scenario -> (rows, S, N)
        return np.moveaxis(arrays[name].reshape(S, rows, N), 0, 1) if name in arrays else np.zeros((rows, S, N))

    return Dispatch(p_unit=stacked("P", G), p_renewable=stacked("Pr", R), p_storage=stacked("Pst", 1)[0],
                    soc=stacked("C", 1)[0], d_load=stacked("D", Dn), p_m=stacked("PM", 1)[0],
                    load_shed=stacked("LS", 1)[0],
                    dp_plus=dp_plus_of(params, scen.subperiods, stacked("PM", 1)[0], stacked("dP", 1)[0]))


def schedule_of(case: Case, scen: ScenarioSet, params: Params, found: Found, trace: Trace, total: float,
                method: str) -> StochasticSchedule:
    """The schedule of what a decomposed search (``method``) found, in ``total`` seconds."""
    summary = trace.summary()
    timings = Timings(build_s=summary["build_s"], solve_s=total - summary["build_s"], total_s=total)
    work_done = {"simplex_iterations": summary["master_simplex_iterations"] + summary["subproblems_simplex_iterations"],
                 "nodes": summary["master_nodes"], "highs_threads": HIGHS_THREADS}
    return found_schedule(case, scen, params, found, timings,
                          {"method": method, "work": work_done, "decomposition": summary, "trace": trace.rows})


def found_schedule(case: Case, scen: ScenarioSet, params: Params, found: Found, timings: Timings,
                   extra: dict | None = None) -> StochasticSchedule:
    """The schedule of a first stage and its dispatch in every scenario (``found``)."""
    pieces, Dn, pr = found.first, len(case.loads), scen.probability
    first = FirstStage(commitment=pieces["I"], startup=pieces["y"], shutdown=pieces["w"],
                       discharging=pieces.get("u", np.zeros(HOURS)), charging=pieces.get("v", np.zeros(HOURS)),
                       load_on=pieces.get("z", np.zeros((Dn, HOURS))))
    expected = {name: exact.dot(pr, values) for name, values in found.costs.items()}
    cost = CostBreakdown(startup=found.startup, **expected)
    return StochasticSchedule(status=found.status, objective=cost.total, bound=min(found.lower, cost.total),
                              cost=cost, first=first, dispatch=_dispatch(case, scen, params, found.arrays),
                              probability=pr.copy(), subperiods=scen.subperiods, penalty=params.penalty,
                              cost_convention=params.cost_convention, take_award=params.take_award,
                              timings=timings, unit_names=tuple(u.name for u in case.units),
                              load_names=tuple(d.name for d in case.loads), extra=extra or {})
