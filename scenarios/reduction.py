"""Scenario reduction by fast forward selection (Heitsch & Römisch 2003) on a matrix of distances between scenarios."""

from __future__ import annotations

import numpy as np


def forward_selection(distance: np.ndarray, probability: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Keep n of S scenarios by fast forward selection; return (kept indices ascending, their new probabilities).

    Algorithm 2.4 of Heitsch & Römisch, "Scenario reduction algorithms in stochastic programming", Comput. Optim.
    Appl. 24 (2003): starting from none, each step adds the scenario u that minimises the Kantorovich distance
    sum_k p_k min(d_k, c(k, u)) of the selection, d_k being scenario k's distance to the scenarios already kept.
    Every deleted scenario then gives its probability to its nearest kept one (their optimal redistribution,
    Theorem 2). Ties go to the lowest index, so the result depends on the data alone.
    """
    distance = np.asarray(distance, dtype=float)
    probability = np.asarray(probability, dtype=float)
    S = len(probability)
    if distance.shape != (S, S):
        raise ValueError(f"distance must be ({S}, {S}) for {S} probabilities, got {distance.shape}")
    if n < 1:
        raise ValueError(f"cannot reduce to {n} scenarios: keep at least 1")
    if n >= S:
        return np.arange(S), probability.copy()
    nearest = np.full(S, np.inf)
    selected = np.zeros(S, dtype=bool)
    for _ in range(n):
        # The only loop is over the n steps; each step scores every candidate u at once in O(S^2).
        score = probability @ np.minimum(distance, nearest[:, None])
        score[selected] = np.inf
        u = int(np.argmin(score))
        selected[u] = True
        nearest = np.minimum(nearest, distance[:, u])
    kept = np.flatnonzero(selected)
    owner = np.argmin(distance[:, kept], axis=1)
    # A kept scenario is at distance 0 from itself, but an exact duplicate of another kept one must not steal it.
    owner[kept] = np.arange(n)
    new_probability = np.bincount(owner, weights=probability, minlength=n)
    return kept, new_probability / new_probability.sum()

