"""How good a schedule is for the uncertainty it was drawn from, not only for its own sample (docs/solver.md,
"Out of sample").

The schedule's first stage (commitment, storage modes, load states) is held fixed and its recourse solved on N
fresh scenarios, drawn as its own were but from another seed: N LPs, warm-started one after another in each
worker (the decomposition's scenario subproblems). The mean of first-stage cost + Q_s(x) estimates the
schedule's true expected cost; its 95% confidence interval is the mean +- 1.96 standard errors (Mak, Morton and
Wood 1999, the upper-bound estimator).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet

from ..model import Params
from ..schedule import StochasticSchedule
from .benders import ScenarioPool, first_stage_vector

Z95 = 1.959963984540054  # the standard normal's 97.5% quantile


@dataclass(frozen=True)
class Evaluation:
    """The schedule's expected cost ($) estimated on ``scenarios`` fresh scenarios, with its 95% interval."""

    scenarios: int
    expected_cost: float
    std_error: float
    low: float
    high: float
    seconds: float

    def as_dict(self) -> dict:
        return asdict(self)


def evaluate_schedule(case: Case, schedule: StochasticSchedule, params: Params, fresh: ScenarioSet,
                      workers: int = 1) -> Evaluation:
    """The first stage of ``schedule`` on the scenarios ``fresh`` (equiprobable, as ``scenarios.sample`` draws
    them): each scenario's recourse solved with that first stage fixed."""
    if fresh.S < 2:
        raise ValueError(f"an out-of-sample evaluation needs at least 2 scenarios, not {fresh.S}")
    start = time.perf_counter()
    pool = ScenarioPool(case, fresh, params, workers)
    try:
        f = schedule.first
        x = first_stage_vector(case, {"I": f.commitment, "y": f.startup, "w": f.shutdown, "u": f.discharging,
                                      "v": f.charging, "z": f.load_on})
        recourse, _ = pool.evaluate(x)
    finally:
        pool.close()
    costs = schedule.cost.startup + recourse
    mean, error = float(costs.mean()), float(costs.std(ddof=1) / math.sqrt(len(costs)))
    return Evaluation(scenarios=fresh.S, expected_cost=mean, std_error=error, low=mean - Z95 * error,
                      high=mean + Z95 * error, seconds=time.perf_counter() - start)


def fresh_seed(seed: int) -> int:
    """The seed of the scenarios an evaluation draws: another stream than the schedule's own (``seed``)."""
    return int(np.random.SeedSequence([seed, 0x0E7A1]).generate_state(1)[0])
