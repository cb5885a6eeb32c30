"""Hourly 0/1 states (unit commitment, storage modes, load states): their start indicators and minimum times.

The paper's counters T^on, T^off, T^ch, T^dch of (6)-(7), (13)-(14) and (17) are replaced by the tight linear
(Rajan-Takriti) form over start indicators, which describes the convex hull of one member's up/down polytope.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from scenarios.horizon import HOURS


def window(length: int) -> np.ndarray:
    """(24, 24) W with W[t, k] = 1 for t - length < k <= t: sums over the last ``length`` hours."""
    t = np.arange(HOURS)
    return ((t[None, :] <= t[:, None]) & (t[None, :] > t[:, None] - length)).astype(float)


def transitions(y: cp.Expression, state: cp.Expression, initial: np.ndarray) -> list[cp.Constraint]:
    """Start indicators y_t = max(0, x_t - x_{t-1}) of an hourly 0/1 state x, exact for binary x; ``initial``
    (rows,) is the state before the day.

    y >= x_t - x_{t-1}, y <= x_t and y <= 1 - x_{t-1} pin y to the positive part, so no later constraint can
    loosen a ramp or a minimum time by inflating y.
    """
    m = state.shape[0]
    before = cp.hstack([np.asarray(initial, float).reshape(m, 1), state[:, :-1]])
    return [y >= state - before, y <= state, y <= 1 - before]


def start_variable(state: cp.Expression, initial: np.ndarray) -> tuple[cp.Variable, list[cp.Constraint]]:
    """A new start-indicator variable of an hourly state, with its defining constraints (``transitions``)."""
    y = cp.Variable(state.shape, bounds=[0, 1])
    return y, transitions(y, state, initial)


def minimum_time(starts: cp.Expression, state: cp.Expression, lengths: np.ndarray) -> list[cp.Constraint]:
    """Tight minimum-time form: the starts within the last L hours may not exceed the state now.

    Used for minimum up time (6) with (starts, state) = (y, I), minimum down time (7) with (w, 1 - I), the
    corrected minimum charge/discharge times (13)-(14) and the minimum operating time of loads (17). Before the
    day a member has been in its initial state long enough: only starts within the day count.
    """
    groups = {}
    for row, length in enumerate(lengths):
        groups.setdefault(int(length), []).append(row)
    out = []
    for length, rows in groups.items():
        if length > 1:
            out.append(starts[rows, :] @ window(length).T <= state[rows, :])
    return out
