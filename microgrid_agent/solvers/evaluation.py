"""How good a schedule is for the uncertainty it was drawn from, not only for its own sample (docs/solver.md,
"Out of sample").

The schedule's first stage (commitment, storage modes, load states) is held fixed and its recourse solved on N
fresh scenarios, drawn as its own were but from another seed: N LPs, warm-started one after another in each
worker (the decomposition's scenario subproblems). The mean of first-stage cost + Q_s(x) estimates the
schedule's true expected cost; its 95% confidence interval is the mean +- 1.96 standard errors (Mak, Morton and
Wood 1999, the upper-bound estimator). With stratified islanding (scenarios.generation.sample) the mean is
weighted by stratum and its standard error is the stratified one.

The optimum of the true problem is bounded below by R independent sample problems: each certified bound
under-estimates its sample's optimum, whose expectation under-estimates the true optimum, so their mean is a
statistical lower bound with a one-sided t interval (MMW's lower-bound estimator). The schedule's optimality gap
for the true distribution is then the evaluation's mean less that bound, with a one-sided 95% upper limit.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

from scenarios import exact
from scenarios.case import Case
from scenarios.generation import ScenarioSet

from ..model import Params
from ..schedule import StochasticSchedule
from .benders import ScenarioPool, first_stage_vector
from .relaxation import islanding_groups

Z95 = float(stats.norm.ppf(0.975))  # two-sided 95%: the evaluation's interval
ONE_SIDED = 0.95  # confidence of the statistical lower bound and of the gap's upper limit


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
                      workers: int = 1, stratified: bool = False) -> Evaluation:
    """The first stage of ``schedule`` on the scenarios ``fresh`` (as ``scenarios.sample`` draws them, with
    ``stratified`` as it was drawn): each scenario's recourse solved with that first stage fixed."""
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
    mean, error = estimate(costs, fresh.probability, islanding_groups(fresh) if stratified else None)
    return Evaluation(scenarios=fresh.S, expected_cost=mean, std_error=error, low=mean - Z95 * error,
                      high=mean + Z95 * error, seconds=time.perf_counter() - start)


def estimate(costs: np.ndarray, probability: np.ndarray, stratum: np.ndarray | None = None) -> tuple[float, float]:
    """The expected cost and its standard error from a sample: equiprobable, or stratified by ``stratum`` (each
    stratum's weight the sum of its members' probabilities, its variance estimated within it). A stratum with a
    single member has no variance of its own; the estimate then falls back to the plain one, which is larger."""
    mean = exact.dot(probability, costs)
    if stratum is not None:
        counts = np.bincount(stratum)
        if counts.min() >= 2:
            weight = np.bincount(stratum, probability)
            centred = costs - (np.bincount(stratum, costs) / counts)[stratum]
            within = np.bincount(stratum, centred ** 2) / (counts - 1)  # each stratum's sample variance
            return mean, float(math.sqrt(np.sum(weight ** 2 * within / counts)))
    return mean, float(costs.std(ddof=1) / math.sqrt(len(costs)))


@dataclass(frozen=True)
class LowerBound:
    """A statistical lower bound of the true optimum from ``replications`` sample problems of ``scenarios`` each."""

    replications: int
    scenarios: int
    bounds: tuple[float, ...]
    estimate: float
    std_error: float
    low: float  # the one-sided 95% lower confidence limit
    seconds: float

    def as_dict(self) -> dict:
        return asdict(self) | {"bounds": list(self.bounds)}


def lower_bound(bounds, scenarios: int, seconds: float) -> LowerBound:
    """MMW's lower-bound estimator from the certified bounds of R >= 2 independent sample problems."""
    bounds = np.asarray(bounds, float)
    if len(bounds) < 2:
        raise ValueError(f"a statistical lower bound needs at least 2 replications, not {len(bounds)}")
    mean, error = estimate(bounds, np.full(len(bounds), 1.0 / len(bounds)))
    low = mean - float(stats.t.ppf(ONE_SIDED, len(bounds) - 1)) * error
    return LowerBound(len(bounds), scenarios, tuple(bounds.tolist()), mean, error, low, seconds)


def optimality_gap(upper: Evaluation, lower: LowerBound) -> dict:
    """The schedule's optimality gap for the true distribution ($): the evaluation's mean less the lower bound, and
    its one-sided 95% upper limit (the two estimates are independent; MMW 1999), absolute and relative to the mean."""
    gap = upper.expected_cost - lower.estimate
    high = max(gap, 0.0) + stats.norm.ppf(ONE_SIDED) * upper.std_error \
        + stats.t.ppf(ONE_SIDED, lower.replications - 1) * lower.std_error
    return {"estimate": gap, "high": float(high), "relative_estimate": gap / abs(upper.expected_cost),
            "relative_high": float(high) / abs(upper.expected_cost)}


def replication_seed(seed: int, r: int) -> int:
    """The seed of replication r's sample problem: a stream apart from the schedule's own and the evaluation's."""
    return int(np.random.SeedSequence([seed, 0x5A4A, r]).generate_state(1)[0])


def fresh_seed(seed: int) -> int:
    """The seed of the scenarios an evaluation draws: another stream than the schedule's own (``seed``)."""
    return int(np.random.SeedSequence([seed, 0x0E7A1]).generate_state(1)[0])
