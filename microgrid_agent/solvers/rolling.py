"""The real-time LP of one microgrid's day, compiled once and re-solved each hour (agent/realtime.py).

Each hour the operator solves the rest of the day with the day-ahead first stage fixed, one scenario (the realised
data so far, the forecast after) and the sub-periods already operated pinned. With the first stage fixed that is
one scenario's LP (scenario_lp.py): its data enter only right-hand sides, so cvxpy compiles it once, the hour's
data re-apply its Parameters, and the first stage, the pinned past and the hour's operating envelope on P_M are
column bounds of one live HiGHS model. Building the model with cvxpy every hour took about 90% of the hour's time.

Each hour is solved from scratch (no basis kept from the hour before), so an hour's plan depends on that hour's
data alone: an agent restarted mid-day operates the same hours as one that was not.

An islanded hour can leave generation with nowhere to go (docs/agent.md, "Feasibility"). The LP carries an outlet
for it beside the model's own columns: per sub-period, the surplus S >= 0 on the demand side of the balance (2),
priced at VOLL like shed load so that it is the last resort, and held at 0 unless ``solve`` is given the
sub-periods where it may be used.
"""

from __future__ import annotations

import time

import highspy
import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet

from ..model import Params, first_stage_variables, startup_cost
from ..schedule import FirstStage, StochasticSchedule, Timings
from .benders import Found, first_stage_vector, found_schedule
from .extensive import SolveError
from .highs import column_bounds, highs_model, row_bounds
from .scenario_lp import ScenarioLP


class RollingLP:
    """One microgrid's real-time LP for a day at ``scen``'s resolution, its first stage fixed at ``first``."""

    def __init__(self, case: Case, params: Params, first: FirstStage, scen: ScenarioSet):
        start = time.perf_counter()
        self.case, self.params, self.first = case, params, first
        self.lp = ScenarioLP(case, params, scen.subperiods, scen.N)
        data, self.columns = self.lp.compile(scen, 0)
        self._take(data)
        held, cols = self.lp.first_stage(self.columns)
        self._fixed = cols, first_stage_vector(case, first_stage_variables(first))[held]
        self.startup = float(startup_cost(case, first_stage_variables(first)).value)
        self._unbooked_s = time.perf_counter() - start  # the compile, counted in the first solve's build time

    def solve(self, scen: ScenarioSet, pinned: tuple[int, dict[str, np.ndarray]] | None = None,
              pm_bounds: tuple[int, np.ndarray, np.ndarray] | None = None,
              time_limit: float | None = None, outlet: tuple[int, int] | None = None
              ) -> tuple[StochasticSchedule, np.ndarray]:
        """The rest of the day on the one-scenario ``scen``, as ``model.build`` takes ``pinned`` (the second-stage
        values of the sub-periods before n0, and with ``"S"`` the surplus let out there) and ``pm_bounds`` (P_M
        within [lower, upper] from sub-period n0); a SolveError if it is infeasible or finds nothing in
        ``time_limit``. ``outlet`` (n0, n1): the islanded sub-periods among n0..n1 may let surplus out. The plan,
        and the surplus (MW) of every sub-period."""
        start = time.perf_counter()
        data, _ = self.lp.compile(scen, 0)
        if _same_matrix(data, self._data):
            lower, upper = row_bounds(data)
            self.h.changeRowsBounds(len(lower), np.arange(len(lower), dtype=np.int32), lower, upper)
        else:  # scenario data reached the matrix (not in today's model): take the model anew
            self._take(data)
        lower, upper = self._column_bounds(data, pinned, pm_bounds)
        let_out = np.zeros(len(self._outlet))
        if outlet is not None:
            islanded = scen.connected[0] < 0.5
            let_out[outlet[0]:outlet[1]] = np.where(islanded[outlet[0]:outlet[1]], highspy.kHighsInf, 0.0)
        held = np.zeros(len(self._outlet))
        if pinned is not None and "S" in pinned[1]:
            held[:pinned[0]] = np.asarray(pinned[1]["S"], float).reshape(-1)[:pinned[0]]
        lower, upper = np.concatenate([lower, held]), np.concatenate([upper, np.maximum(held, let_out)])
        self.h.changeColsBounds(len(lower), np.arange(len(lower), dtype=np.int32), lower, upper)
        self.h.clearSolver()
        self.h.setOptionValue("time_limit", float(time_limit) if time_limit else highspy.kHighsInf)
        built = time.perf_counter()
        self.h.run()
        status = self.h.getModelStatus()
        if status != highspy.HighsModelStatus.kOptimal:
            raise SolveError(f"the real-time LP is {self.h.modelStatusToString(status)}"
                             + (f" (time limit {time_limit} s)" if status == highspy.HighsModelStatus.kTimeLimit
                                else ""))
        col = np.asarray(self.h.getSolution().col_value)
        model, surplus = col[:-len(self._outlet)], np.maximum(col[self._outlet], 0.0)
        arrays, costs = self.lp.read(self.columns, model)
        found = Found(first_stage_variables(self.first), self.startup, {n: a[None] for n, a in arrays.items()},
                      {n: np.array([c]) for n, c in costs.items()},
                      self.startup + self.h.getInfo().objective_function_value, "optimal")
        end = time.perf_counter()
        build_s, self._unbooked_s = built - start + self._unbooked_s, 0.0
        return found_schedule(self.case, scen, self.params, found,
                              Timings(build_s=build_s, solve_s=end - built, total_s=build_s + end - built)), surplus

    def _take(self, data: dict) -> None:
        """A live HiGHS model of ``data``, with the outlet's columns after the model's: each the negative of the
        shed load's column in its balance row (2), at its cost."""
        self.h, self._data = highs_model(data, integer=False), data
        shed = self.columns.of(self.lp.var["LS"])
        balance = data["A"].tocsc()[:data["dims"].zero][:, shed]  # the equality rows: (2) holds LS once
        if not np.all(np.diff(balance.indptr) == 1):
            raise ValueError("the shed load is not in exactly one balance row of each sub-period")
        n, first = len(shed), data["A"].shape[1]
        self.h.addCols(n, np.asarray(data["c"], float)[shed], np.zeros(n), np.zeros(n), n,
                       np.arange(n, dtype=np.int32), balance.indices.astype(np.int32), -balance.data)
        self._outlet = np.arange(first, first + n, dtype=np.int32)

    def _column_bounds(self, data: dict, pinned, pm_bounds) -> tuple[np.ndarray, np.ndarray]:
        lower, upper = (bound.copy() for bound in column_bounds(data))
        cols, x = self._fixed
        lower[cols] = upper[cols] = x
        if pinned is not None and pinned[0] > 0:
            n0, values = pinned
            for name, value in values.items():
                var = self.lp.var.get(name)
                if var is not None and self.columns.holds(var):
                    past = self.columns.shaped(var)[:, :n0]
                    lower[past] = upper[past] = np.asarray(value, float).reshape(var.shape)[:, :n0]
        if pm_bounds is not None:
            n0, low, high = pm_bounds
            now = self.columns.shaped(self.lp.var["PM"])[:, n0:n0 + len(low)]
            lower[now], upper[now] = np.asarray(low, float)[None, :], np.asarray(high, float)[None, :]
        return lower, upper


def _same_matrix(a: dict, b: dict) -> bool:
    A, B = a["A"], b["A"]
    return (A.shape == B.shape and np.array_equal(A.indptr, B.indptr) and np.array_equal(A.indices, B.indices)
            and np.array_equal(A.data, B.data) and np.array_equal(a["c"], b["c"]))
