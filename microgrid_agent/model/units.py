"""Dispatchable units i in G: commitment with minimum up/down times (6)-(7), output limits (3) and ramps (4)-(5)."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from scenarios.case import Case
from scenarios.horizon import HOURS

from .index import Index, previous
from .states import minimum_time, transitions


def commitment(case: Case, v: dict) -> list[cp.Constraint]:
    """First stage of the units: start-up (y) and shut-down (w) indicators and minimum up/down times (6)-(7).

    Counters T^on/T^off are replaced by the tight linear form over y and w (states.py). Before the day each unit
    is in its case's ``initial_on`` state; unless its ``initial_hours`` say otherwise it has been so long enough,
    so a unit off at midnight may start in hour 1 and one on at midnight may shut down in hour 1. With
    ``initial_hours`` (a day that follows another), it keeps its state for the hours (6)-(7) still ask
    (docs/model.md, "Conventions the paper leaves open").
    """
    I, y, w = v["I"], v["y"], v["w"]
    initial = case.unit_array("initial_on")
    cons = [
        *transitions(y, I, initial), *transitions(w, 1 - I, 1 - initial),
        *minimum_time(y, I, case.unit_array("min_up")),  # (6)
        *minimum_time(w, 1 - I, case.unit_array("min_down")),  # (7)
    ]
    keep = kept_initial_state(case)
    if keep.any():  # (6)-(7) across midnight: the hours the day before leaves owing
        cons.append(cp.multiply(keep, I) == keep * initial[:, None])
    return cons


def kept_initial_state(case: Case) -> np.ndarray:
    """(G, 24) 0/1: 1 where a unit must still be in its initial state, by ``Unit.keep_initial_hours``."""
    keep = case.unit_array("keep_initial_hours")
    return (np.arange(HOURS)[None, :] < keep[:, None]).astype(float)


def shutdown_after_ramping_down(case: Case, v: dict, dt: float) -> list[cp.Constraint]:
    """A unit on since midnight reaches its shut-down step (5) only once ramps have brought it from its initial
    output P0 to at most P_min + RD dt: a first shut-down in hour t >= 2 needs (t - 1) RD + RD dt >= P0 - P_min.

    In hour 1 it may shut down from P0 itself (docs/model.md). Where the inequality fails, w_t = 1 is allowed only
    after an earlier shut-down (w_t <= sum of w before t), which broke the ramp from P0. The sub-period model
    implies this; it is stated here so that the master of the decomposition, whose hourly relaxation ramps a whole
    hour in one step, proposes no first stage without a feasible dispatch (docs/solver.md).
    """
    p0, p_min, rd = (case.unit_array(k)[:, None] for k in ("initial_output", "p_min", "ramp_down"))
    t = np.arange(1, HOURS + 1)[None, :]
    unit, hour = np.nonzero((t >= 2) & ((t - 1) * rd + rd * dt < p0 - p_min - 1e-9))
    if not len(unit):
        return []
    w = v["w"]
    earlier = cp.cumsum(w, axis=1) - w  # sum of w over the hours before t
    return [w[unit, hour] <= earlier[unit, hour]]


def unit_dispatch(case: Case, ix: Index, v: dict) -> list[cp.Constraint]:
    """Dispatch of the units: limits (3) and ramps (4)-(5), the ramps scaled by the commitment.

    Departures from the printed form (docs/model.md): ramps hold between every pair of consecutive sub-periods,
    across hour boundaries too, as rates UR dt per sub-period, and a start-up (shut-down) may jump from (to) zero
    through the minimum output in one step. Written as P_n - P_{n-1} <= (P_min + UR dt) I(n) - P_min I(n-1) and
    its mirror, they allow exactly the dispatches of the paper's form at every binary commitment, and cut off
    the fractional commitments that would ramp like whole units in the LP relaxation (a tighter bound).
    """
    G = len(case.units)
    P = v["P"]
    p_min, p_max = case.unit_array("p_min"), case.unit_array("p_max")
    I_n = ix.expand(v["I"], G)
    I_prev = previous(np.repeat(case.unit_array("initial_on"), ix.S), I_n)  # the commitment one sub-period before
    initial = np.repeat(case.unit_array("initial_output"), ix.S)
    p_prev = previous(initial, P)
    step = ix.per_row(p_min)
    # A shut-down steps from P_min to 0; at midnight, from the output the day starts with (the previous day could
    # have ramped it down), so every first stage keeps a feasible dispatch.
    step_down = step.copy()
    step_down[:, 0] = initial
    up, down = ix.per_row(case.unit_array("ramp_up") * ix.dt), ix.per_row(case.unit_array("ramp_down") * ix.dt)
    return [
        P >= cp.multiply(step, I_n),  # (3)
        P <= cp.multiply(ix.per_row(p_max), I_n),  # (3)
        P - p_prev <= cp.multiply(step + up, I_n) - cp.multiply(step, I_prev),  # (4)
        p_prev - P <= cp.multiply(step_down + down, I_prev) - cp.multiply(step_down, I_n),  # (5)
    ]
