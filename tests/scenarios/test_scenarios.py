"""Scenario generation, reduction by fast forward selection, and the expected-value and single-scenario views."""

import numpy as np
import pytest
from scipy.spatial.distance import cdist

from scenarios.case import load_case
from scenarios.generation import (
    ScenarioSet,
    expected_value,
    make_scenarios,
    reduce_scenarios,
    sample,
)
from scenarios.reduction import forward_selection

CASE = load_case("paper")
K = 3  # sub-periods per hour: small arrays, same logic as the paper's 6


def step(forecast, k=K):
    return np.repeat(np.asarray(forecast, dtype=float), k)


def island_start(scen: ScenarioSet) -> np.ndarray:
    """0-based start hour of each scenario's islanding event."""
    return np.argmax(scen.connected == 0, axis=1) // scen.subperiods


def test_shapes_and_probabilities():
    scen = sample(CASE, 7, subperiods=K)
    N = 24 * K
    assert (scen.S, scen.N, scen.dt) == (7, N, 1 / K)
    assert scen.load.shape == (7, N)
    assert scen.renewable.shape == (len(CASE.renewables), 7, N)
    assert scen.connected.shape == (7, N)
    np.testing.assert_allclose(scen.probability, np.full(7, 1 / 7))


def test_same_seed_same_draws_other_seed_others():
    a, b, c = (sample(CASE, 5, subperiods=K, seed=s) for s in (3, 3, 4))
    for field in ("load", "renewable", "connected", "probability"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(a.load, c.load)
    assert not np.array_equal(a.renewable, c.renewable)


def test_scenario_draws_do_not_depend_on_sample_size():
    small, large = sample(CASE, 4, subperiods=K, seed=9), sample(CASE, 11, subperiods=K, seed=9)
    np.testing.assert_array_equal(small.load, large.load[:4])
    np.testing.assert_array_equal(small.renewable, large.renewable[:, :4])
    np.testing.assert_array_equal(small.connected, large.connected[:4])


def test_load_errors_within_bounds_and_both_signs():
    scen = sample(CASE, 200, subperiods=K)
    error = scen.load / step(CASE.fixed_load.forecast) - 1
    bound = CASE.uncertainty.load
    assert np.abs(error).max() <= bound + 1e-12
    assert error.max() > 0.9 * bound and error.min() < -0.9 * bound


def test_renewables_clipped_to_capacity_and_errors_within_bounds():
    scen = sample(CASE, 200, subperiods=K)
    for r, unit in enumerate(CASE.renewables):
        avail, forecast = scen.renewable[r], step(unit.forecast)
        bound = CASE.uncertainty.for_renewable(unit.name)
        assert avail.min() >= 0 and avail.max() <= unit.capacity
        assert np.all(avail[:, forecast == 0] == 0)
        unclipped = (forecast > 0) & (avail < unit.capacity)
        error = avail / np.where(forecast > 0, forecast, 1) - 1
        assert np.abs(error[unclipped]).max() <= bound + 1e-12
        assert error[unclipped].max() > 0.5 * bound and error[unclipped].min() < -0.9 * bound
    w = [u.name for u in CASE.renewables].index("wind")
    # The wind forecast reaches 0.85 MW and +30% would exceed its 1 MW: those draws must sit at capacity.
    assert np.any(scen.renewable[w] == CASE.renewables[w].capacity)


@pytest.mark.parametrize("hours", [1, 3, 24])
def test_islanding_is_h_contiguous_whole_hours(hours):
    scen = sample(CASE, 2000, subperiods=K, island_hours=hours)
    islanded = scen.connected == 0
    assert set(np.unique(scen.connected)) <= {0.0, 1.0}
    assert np.all(islanded.sum(axis=1) == hours * K)
    start = np.argmax(islanded, axis=1)
    assert np.all(start % K == 0)
    span = np.arange(24 * K)
    expected = (span >= start[:, None]) & (span < start[:, None] + hours * K)
    np.testing.assert_array_equal(islanded, expected)
    assert set(island_start(scen) + 1) == set(range(1, 24 - hours + 2))


def test_no_islanding_is_always_connected():
    assert np.all(sample(CASE, 20, subperiods=K, island_hours=0).connected == 1)


def test_islanding_duration_keeps_forecast_errors_and_start_draws():
    base = sample(CASE, 300, subperiods=K, island_hours=1, seed=5)
    for hours in (0, 2, 5):
        other = sample(CASE, 300, subperiods=K, island_hours=hours, seed=5)
        np.testing.assert_array_equal(base.load, other.load)
        np.testing.assert_array_equal(base.renewable, other.renewable)
    # Start = floor(u (25 - H)) from the same u: one more hour moves a start back by at most one hour.
    for hours in (1, 2, 5):
        shorter = island_start(sample(CASE, 300, subperiods=K, island_hours=hours, seed=5))
        longer = island_start(sample(CASE, 300, subperiods=K, island_hours=hours + 1, seed=5))
        assert np.all((shorter - longer >= 0) & (shorter - longer <= 1))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n": 0}, "n must be"),
        ({"n": 3, "subperiods": 0}, "subperiods"),
        ({"n": 3, "island_hours": -1}, "island_hours"),
        ({"n": 3, "island_hours": 25}, "island_hours"),
    ],
)
def test_sample_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        sample(CASE, **kwargs)


def test_forward_selection_by_hand():
    # Points 0, 1, 10: first 1 (expected distance 10/3 is least), then 10 (leaves only 0->1, 1/3).
    x = np.array([0.0, 1.0, 10.0])
    kept, probability = forward_selection(np.abs(x[:, None] - x[None, :]), np.full(3, 1 / 3), 2)
    np.testing.assert_array_equal(kept, [1, 2])
    np.testing.assert_allclose(probability, [2 / 3, 1 / 3])


def test_forward_selection_beats_random_selections():
    rng = np.random.default_rng(42)
    points = rng.normal(size=(80, 4))
    p = rng.dirichlet(np.ones(80))
    distance = cdist(points, points)

    def kantorovich(kept):
        return p @ distance[:, kept].min(axis=1)

    kept, probability = forward_selection(distance, p, 10)
    random_best = min(kantorovich(rng.choice(80, 10, replace=False)) for _ in range(200))
    assert kantorovich(kept) <= random_best
    owner = kept[np.argmin(distance[:, kept], axis=1)]
    np.testing.assert_allclose(probability, [p[owner == j].sum() for j in kept])


def test_reduce_keeps_n_with_probabilities_summing_to_one():
    scen = sample(CASE, 120, subperiods=K, seed=1)
    reduced = reduce_scenarios(scen, 15)
    assert reduced.S == 15
    assert np.all(reduced.probability >= 0)
    assert reduced.probability.sum() == pytest.approx(1)
    # Kept scenarios are rows of the sample, in their original order.
    rows = [int(np.flatnonzero((scen.load == row).all(axis=1))[0]) for row in reduced.load]
    assert rows == sorted(rows)
    np.testing.assert_array_equal(reduced.renewable, scen.renewable[:, rows])
    np.testing.assert_array_equal(reduced.connected, scen.connected[rows])


def test_reduce_merges_exact_duplicates():
    distinct = sample(CASE, 8, subperiods=K, seed=2)
    order = np.random.default_rng(0).permutation(16)
    twice = ScenarioSet(
        subperiods=K,
        probability=np.full(16, 1 / 16),
        load=np.concatenate([distinct.load, distinct.load])[order],
        renewable=np.concatenate([distinct.renewable, distinct.renewable], axis=1)[:, order],
        connected=np.concatenate([distinct.connected, distinct.connected])[order],
    )
    reduced = reduce_scenarios(twice, 8)
    group = [int(np.flatnonzero((distinct.load == row).all(axis=1))[0]) for row in reduced.load]
    assert sorted(group) == list(range(8))
    np.testing.assert_allclose(reduced.probability, np.full(8, 2 / 16))


def test_reduce_edge_cases():
    scen = sample(CASE, 5, subperiods=K)
    assert reduce_scenarios(scen, 5) is scen
    assert reduce_scenarios(scen, 9) is scen
    with pytest.raises(ValueError, match="at least 1"):
        reduce_scenarios(scen, 0)


def test_make_scenarios_reduces_a_larger_sample():
    reduced = make_scenarios(CASE, 6, subperiods=K, seed=4)
    pool = sample(CASE, 60, subperiods=K, seed=4)
    assert reduced.S == 6 and reduced.probability.sum() == pytest.approx(1)
    assert all(np.any((pool.load == row).all(axis=1)) for row in reduced.load)
    unreduced = make_scenarios(CASE, 6, subperiods=K, seed=4, sample_size=6)
    np.testing.assert_array_equal(unreduced.load, sample(CASE, 6, subperiods=K, seed=4).load)
    with pytest.raises(ValueError, match="sample_size"):
        make_scenarios(CASE, 6, sample_size=5)


def test_expected_value_is_the_weighted_mean():
    scen = reduce_scenarios(sample(CASE, 60, subperiods=K, island_hours=2, seed=3), 12)
    p = scen.probability
    ev = expected_value(scen)
    assert ev.S == 1 and ev.probability.tolist() == [1.0]
    np.testing.assert_allclose(ev.load[0], p @ scen.load)
    np.testing.assert_allclose(ev.renewable[:, 0], np.tensordot(scen.renewable, p, axes=([1], [0])))
    np.testing.assert_allclose(ev.connected[0], p @ scen.connected)
    assert np.all((ev.connected >= 0) & (ev.connected <= 1))
    # Every scenario is islanded for 2 hours, so the expected islanded time is exactly 2 hours.
    assert (1 - ev.connected).sum() * ev.dt == pytest.approx(2)


def test_subset_and_single():
    scen = reduce_scenarios(sample(CASE, 40, subperiods=K, seed=6), 8)
    part = scen.subset([1, 4, 6])
    np.testing.assert_allclose(part.probability, scen.probability[[1, 4, 6]] / scen.probability[[1, 4, 6]].sum())
    np.testing.assert_array_equal(part.load, scen.load[[1, 4, 6]])
    np.testing.assert_array_equal(part.renewable, scen.renewable[:, [1, 4, 6]])
    mask = np.zeros(8, dtype=bool)
    mask[[1, 4, 6]] = True
    np.testing.assert_array_equal(scen.subset(mask).load, part.load)
    one = scen.single(3)
    assert one.S == 1 and one.probability.tolist() == [1.0]
    np.testing.assert_array_equal(one.connected[0], scen.connected[3])
    with pytest.raises(ValueError, match="at least one"):
        scen.subset([])


@pytest.mark.parametrize("n, hours", [(100, 1), (48, 1), (30, 3)])
def test_stratified_islanding_covers_every_start_hour_evenly_with_its_true_weight(n, hours):
    case = load_case("paper")
    scen = sample(case, n, 1, island_hours=hours, seed=4, stratified=True)
    start = (1 - scen.connected).argmax(axis=1)
    m = 25 - hours
    counts = np.bincount(start, minlength=m)
    assert len(counts) == m and counts.min() == n // m and counts.max() <= n // m + 1
    assert scen.probability.sum() == pytest.approx(1.0)
    # every start hour carries 1/m, the chance that an H-hour event starts there
    assert np.bincount(start, scen.probability, minlength=m) == pytest.approx(np.full(m, 1 / m))
    assert (1 - scen.connected).sum(axis=1).tolist() == [hours] * n
    # forecast errors are drawn as without stratification
    assert np.array_equal(scen.load, sample(case, n, 1, island_hours=hours, seed=4).load)


def test_stratified_islanding_with_fewer_scenarios_than_start_hours_picks_distinct_equiprobable_hours():
    scen = sample(load_case("paper"), 10, 1, island_hours=1, seed=4, stratified=True)
    start = (1 - scen.connected).argmax(axis=1)
    assert len(set(start.tolist())) == 10 and np.allclose(scen.probability, 0.1)
    other = (1 - sample(load_case("paper"), 10, 1, island_hours=1, seed=5, stratified=True).connected).argmax(axis=1)
    assert set(other.tolist()) != set(start.tolist())  # the order of the hours is random
