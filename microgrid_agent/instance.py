"""One scheduling instance: a case, its scenario set and the award/penalty it is solved against."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet, make_scenarios

from .model import Params
from .schedule import FirstStage, StochasticSchedule
from .solvers.extensive import solve
from .solvers.routes import resolve_method


@dataclass(frozen=True)
class Instance:
    case: Case
    scen: ScenarioSet
    params: Params

    def solve(self, method: str = "extensive", workers: int = 2, progress=None, start: FirstStage | None = None,
              **options) -> StochasticSchedule:
        """The extensive form (reference), the Benders decomposition, or the decomposition in one tree (or "auto": by
        scenario count and resolution); each certifies its gap. ``progress(message)`` hears of each Benders
        iteration (the extensive form reports through HiGHS's own log, ``verbose``). ``start``, a first stage (the
        day before's), is the Benders search's first incumbent if feasible; the other routes do without
        (docs/solver.md, "The decomposition")."""
        route = resolve_method(method, self.scen.S, self.scen.subperiods)
        if route in ("benders", "tree"):
            known = {k: v for k, v in options.items() if k in ("gap", "time_limit")}
            if route == "benders":
                from .solvers.benders import solve_decomposed  # noqa: PLC0415
                return solve_decomposed(self.case, self.scen, self.params, workers=workers, progress=progress,
                                        start=start, **known)
            from .solvers.tree import solve_tree  # noqa: PLC0415
            return solve_tree(self.case, self.scen, self.params, workers=workers, progress=progress, **known)
        return solve(self.case, self.scen, self.params, **options)


def make_instance(
    case: Case,
    *,
    scenarios: int = 10,
    subperiods: int = 6,
    island_hours: int = 1,
    transfer_scale: float = 1.0,
    penalty: float | None = None,
    seed: int = 0,
    sample_size: int | None = None,
    cost_convention: str = "real",
    take_award: bool = False,
    stratified: bool = False,
) -> Instance:
    """The case's Table I award scaled by ``transfer_scale`` (Fig. 3), its penalty unless given (Fig. 5), and
    ``scenarios`` reduced from a seeded sample with ``island_hours`` of islanding each (Fig. 2). With
    ``take_award`` the award must be taken while connected, not only kept below (docs/model.md); with
    ``stratified`` the sample spreads the islanding evenly over the day (scenarios.generation.sample)."""
    scen = make_scenarios(case, scenarios, subperiods, island_hours, seed=seed, sample_size=sample_size,
                          stratified=stratified)
    p_sch = np.asarray(case.grid.p_sch, float) * transfer_scale
    c = case.grid.penalty if penalty is None else float(penalty)
    return Instance(case, scen, Params(p_sch, c, cost_convention, take_award=take_award))
