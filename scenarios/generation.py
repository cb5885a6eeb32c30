"""Scenario sets of the uncertain data: sub-hourly forecast errors of fixed load and renewables, and islanding."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from scenarios.case import Case
from scenarios.horizon import HOURS, per_subperiod, subperiod_hours
from scenarios.reduction import forward_selection

# Independent random streams per quantity, so that changing one input (the islanding duration, the number of
# renewables, n) leaves the other draws as they were: a sweep over H then compares costs under the same errors.
_LOAD_STREAM = 0
_ISLAND_STREAM = 1
_RENEWABLE_STREAM = 2
# The most scenarios a schedule may have (after reduction): ten times the paper's 100. The reduction's distances
# take O(sample^2) memory, so the sample drawn before it is bounded too: reducing 10,000 to 1,000 (the default
# sample of 10 n at this bound) peaks at 2.4 GiB and takes 142 s on the 2-core machine; a sample that is not
# reduced (an evaluation's) costs 8 bytes x 24 K x (2 + renewables) per scenario, 59 MiB for 10,000 at K = 6.
MAX_SCENARIOS = 1_000
MAX_SAMPLE = 10_000


@dataclass(frozen=True)
class ScenarioSet:
    """S scenarios at K sub-periods per hour (N = 24 K), with probabilities pr_s of objective (1).

    ``load`` (S, N): fixed load, MW. ``renewable`` (R, S, N): availability of each renewable, MW (ordered as
    the case's renewables). ``connected`` (S, N): U of (18), 1 grid-connected and 0 islanded.
    """

    subperiods: int
    probability: np.ndarray
    load: np.ndarray
    renewable: np.ndarray
    connected: np.ndarray

    @property
    def S(self) -> int:
        return len(self.probability)

    @property
    def N(self) -> int:
        return HOURS * self.subperiods

    @property
    def dt(self) -> float:
        return subperiod_hours(self.subperiods)

    def subset(self, index) -> ScenarioSet:
        """The scenarios at ``index`` (integers or a boolean mask over S), their probabilities renormalised to 1."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        if index.size == 0:
            raise ValueError("a scenario subset needs at least one scenario")
        probability = self.probability[index]
        total = probability.sum()
        if total <= 0:
            raise ValueError(f"scenarios {index.tolist()} have zero total probability")
        return self._take(index, probability / total)

    def single(self, s: int) -> ScenarioSet:
        """Scenario s alone with probability 1, as the wait-and-see problem of the EVPI solves it."""
        return self.subset([s])

    def _take(self, index: np.ndarray, probability: np.ndarray) -> ScenarioSet:
        return replace(
            self,
            probability=probability,
            load=self.load[index],
            renewable=self.renewable[:, index],
            connected=self.connected[index],
        )


def sample(case: Case, n: int, subperiods: int = 6, island_hours: int = 1, seed: int = 0,
           stratified: bool = False) -> ScenarioSet:
    """n scenarios of the case's uncertain data at ``subperiods`` sub-periods per hour, equiprobable unless
    ``stratified``.

    Section IV of the paper draws each scenario as "a uniformly distributed random nondispatchable unit
    generation and load": the forecast of a sub-period is the hourly forecast of its hour, and the fixed load is
    forecast x (1 + e), e ~ U(-b, b) independently per scenario and sub-period, b = ``case.uncertainty.load``.
    Each renewable is drawn the same way with its own bound and clipped to [0, capacity]. Islanding sets the
    binary U of (18): with ``island_hours`` H > 0 every scenario is islanded for H consecutive whole hours,
    starting at an hour drawn uniformly from 1..24-H+1; H = 0 is always grid-connected.

    Errors are drawn as unit draws scaled by their bound, and the start hour as 1 + floor(u (25 - H)) from one
    u ~ U[0, 1) per scenario, each quantity from its own stream of ``seed``: the same seed gives the same
    errors whatever H, the bounds or n (scenario s is the same in a larger sample), and neighbouring H start
    their events from the same u.

    ``stratified`` spreads the islanding evenly over the m = 25 - H possible start hours instead: the start hours
    of scenarios 1, 2, ... follow one random order of all m, over and over, so each hour starts the event in
    n // m or n // m + 1 scenarios. With n >= m every start hour is a stratum of probability 1/m, shared equally
    by its scenarios (the probabilities then differ by at most a factor (n // m + 1) / (n // m)); with n < m the n
    hours are distinct and equiprobable. Either way each scenario's cost is weighted as its start hour's true
    probability asks, so expectations stay unbiased (``stratum_weights``). Forecast errors are drawn as before.
    """
    if not 1 <= n <= MAX_SAMPLE:
        raise ValueError(f"n must be 1..{MAX_SAMPLE} scenarios, got {n}")
    if subperiods < 1:
        raise ValueError(f"subperiods must be at least 1 per hour, got {subperiods}")
    if not 0 <= island_hours <= HOURS:
        raise ValueError(f"island_hours must be within 0..{HOURS}, got {island_hours}")
    N = HOURS * subperiods

    def perturbed(forecast, bound: float, stream: int) -> np.ndarray:
        unit_error = np.random.default_rng([seed, stream]).uniform(-1.0, 1.0, size=(n, N))
        return per_subperiod(np.asarray(forecast, dtype=float), subperiods) * (1.0 + bound * unit_error)

    load = perturbed(case.fixed_load.forecast, case.uncertainty.load, _LOAD_STREAM)
    renewable = np.zeros((len(case.renewables), n, N))
    for r, unit in enumerate(case.renewables):
        bound = case.uncertainty.for_renewable(unit.name)
        renewable[r] = np.clip(perturbed(unit.forecast, bound, _RENEWABLE_STREAM + r), 0.0, unit.capacity)

    m = HOURS - island_hours + 1  # start hours an H-hour event can have
    islands = np.random.default_rng([seed, _ISLAND_STREAM])
    if stratified:
        start = islands.permutation(m)[np.arange(n) % m]
    else:
        start = np.floor(islands.random(n) * m).astype(int)  # 0-based hour
    probability = np.full(n, 1.0 / n)
    if stratified and island_hours > 0 and n >= m:
        probability = stratum_weights(start, np.full(m, 1.0 / m))
    hour = np.arange(HOURS)
    islanded = (start[:, None] <= hour) & (hour < start[:, None] + island_hours)
    connected = per_subperiod(1.0 - islanded, subperiods)

    return ScenarioSet(
        subperiods=subperiods,
        probability=probability,
        load=load,
        renewable=renewable,
        connected=connected,
    )


def stratum_weights(stratum: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Each member's probability when stratum h, of true probability ``mass[h]``, is shared equally by its members."""
    counts = np.bincount(stratum, minlength=len(mass))
    return mass[stratum] / counts[stratum]


def scenario_distances(scen: ScenarioSet) -> np.ndarray:
    """(S, S) Euclidean distances between scenarios' feature vectors, the cost c of the scenario reduction.

    A scenario's features, one per sub-period each: the fixed load's relative deviation, (load - m) / m, m the
    probability-weighted mean load of that sub-period (the set does not carry the forecast; m estimates it and
    makes the feature the relative forecast error up to a shift that distances cancel); each renewable's
    deviation in MW over that renewable's largest availability in the set (a stand-in for its capacity, so
    wind and solar weigh by their size relative to themselves, not in MW); and the islanding indicator 1 - U.
    With the paper's bounds, islanding in a different hour (2K differing ones) outweighs a whole day of forecast
    errors, as it does in cost.
    """
    p = scen.probability
    mean_load = p @ scen.load
    load_scale = np.where(mean_load > 0, mean_load, 1.0)
    peak = scen.renewable.max(axis=(1, 2), initial=0.0)
    renewable_scale = np.where(peak > 0, peak, 1.0)[:, None, None]
    mean_renewable = np.einsum("s,rsn->rn", p, scen.renewable)[:, None, :]
    features = np.concatenate(
        [
            (scen.load - mean_load) / load_scale,
            *((scen.renewable - mean_renewable) / renewable_scale),
            1.0 - scen.connected,
        ],
        axis=1,
    )
    # The Gram-matrix form uses BLAS and O(S^2) memory; centring the features first keeps it accurate.
    features = features - features.mean(axis=0)
    norm = np.einsum("sf,sf->s", features, features)
    squared = norm[:, None] + norm[None, :] - 2.0 * features @ features.T
    distance = np.sqrt(np.maximum(squared, 0.0))
    np.fill_diagonal(distance, 0.0)
    return distance


def reduce_scenarios(scen: ScenarioSet, n: int) -> ScenarioSet:
    """The n scenarios kept by fast forward selection (Heitsch & Römisch 2003) under ``scenario_distances``.

    Deleted scenarios give their probability to their nearest kept one; the kept scenarios stay in their
    original order. With n >= S the set is returned unchanged.
    """
    if n < 1:
        raise ValueError(f"cannot reduce to {n} scenarios: keep at least 1")
    if n >= scen.S:
        return scen
    kept, probability = forward_selection(scenario_distances(scen), scen.probability, n)
    return scen._take(kept, probability)


def make_scenarios(
    case: Case,
    n: int,
    subperiods: int = 6,
    island_hours: int = 1,
    seed: int = 0,
    sample_size: int | None = None,
    stratified: bool = False,
) -> ScenarioSet:
    """The paper's "reduced 100 scenarios": ``sample_size`` sampled scenarios (default 10 n) reduced to n; with
    ``stratified``, the sample spreads the islanding evenly over the day (``sample``)."""
    if not 1 <= n <= MAX_SCENARIOS:
        raise ValueError(f"a schedule has 1..{MAX_SCENARIOS} scenarios, not {n}")
    size = 10 * n if sample_size is None else sample_size
    if not n <= size <= MAX_SAMPLE:
        raise ValueError(f"sample_size ({size}) must be at least n ({n}) and at most {MAX_SAMPLE}")
    return reduce_scenarios(sample(case, size, subperiods, island_hours, seed, stratified), n)


def expected_value(scen: ScenarioSet) -> ScenarioSet:
    """One scenario of probability 1 holding the probability-weighted means, for the value of the stochastic solution.

    ``connected`` becomes the probability of being grid-connected in each sub-period, a fractional U in [0, 1]:
    the expected-value problem sees a partial limit on the grid transfer rather than an islanding event.
    """
    p = scen.probability
    return ScenarioSet(
        subperiods=scen.subperiods,
        probability=np.ones(1),
        load=(p @ scen.load)[None, :],
        renewable=np.einsum("s,rsn->rn", p, scen.renewable)[:, None, :],
        connected=(p @ scen.connected)[None, :],
    )


def clipped_mean(forecast: np.ndarray, bound: float, capacity: float) -> np.ndarray:
    """E[min(f (1 + b e), cap)] for e ~ U(-1, 1): the mean availability ``sample`` draws (clipped at capacity).

    Where f (1 + b) <= cap nothing is clipped and the mean is f. Otherwise, with e* = (cap / f - 1) / b the error
    at which the clip starts, the mean is (1/2) [f ((e* + 1) + b (e*^2 - 1) / 2) + cap (1 - e*)].
    """
    f = np.asarray(forecast, float)
    clipped = (bound > 0) & (f * (1.0 + bound) > capacity)
    safe_f = np.where(clipped, f, 1.0)
    e = np.where(clipped, (capacity / safe_f - 1.0) / max(bound, 1e-300), 1.0)
    mean = 0.5 * (safe_f * ((e + 1.0) + bound * (e * e - 1.0) / 2.0) + capacity * (1.0 - e))
    return np.where(clipped, mean, f)


def forecast_scenario(case: Case, subperiods: int) -> ScenarioSet:
    """One grid-connected scenario of probability 1 holding the exact expected load and renewable availability
    of ``sample`` (the forecast; renewables slightly below it where the error is clipped)."""
    if subperiods < 1:
        raise ValueError(f"subperiods must be at least 1 per hour, got {subperiods}")
    load = per_subperiod(np.asarray(case.fixed_load.forecast, float), subperiods)[None, :]
    renewable = np.zeros((len(case.renewables), 1, HOURS * subperiods))
    for r, unit in enumerate(case.renewables):
        mean = clipped_mean(np.asarray(unit.forecast), case.uncertainty.for_renewable(unit.name), unit.capacity)
        renewable[r, 0] = per_subperiod(mean, subperiods)
    return ScenarioSet(subperiods, np.ones(1), load, renewable, np.ones((1, HOURS * subperiods)))
