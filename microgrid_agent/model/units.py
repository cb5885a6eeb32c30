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
    """Dispatch of the units: limits (3) and ramps (4)-(5).

    Departures from the printed form (docs/model.md): ramps hold between every pair of consecutive sub-periods,
    across hour boundaries too, as rates UR dt per sub-period, and allow a start-up (shut-down) to jump from
    (to) zero through the minimum output in one step.
    """
    G = len(case.units)
    P = v["P"]
    p_min, p_max = case.unit_array("p_min"), case.unit_array("p_max")
    I_n = ix.expand(v["I"], G)
    initial = np.repeat(case.unit_array("initial_output"), ix.S)
    p_prev = previous(initial, P)
    allowance = cp.multiply(ix.per_row(p_min), ix.at_hour_start(v["y"], G))
    # A shut-down steps from P_min to 0; at midnight, from the output the day starts with (the previous day
    # could have ramped it down), so every first stage keeps a feasible dispatch.
    step_down = ix.per_row(p_min)
    step_down[:, 0] = initial
    allowance_down = cp.multiply(step_down, ix.at_hour_start(v["w"], G))
    return [
        P >= cp.multiply(ix.per_row(p_min), I_n),  # (3)
        P <= cp.multiply(ix.per_row(p_max), I_n),  # (3)
        P - p_prev <= ix.per_row(case.unit_array("ramp_up") * ix.dt) + allowance,  # (4)
        p_prev - P <= ix.per_row(case.unit_array("ramp_down") * ix.dt) + allowance_down,  # (5)
    ]
