"""Adjustable loads d in D: operating window [alpha_d, beta_d] and minimum operating time (17), power limits (15)
and energy within the window (16)."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from scenarios.case import Case

from .index import Index
from .states import minimum_time, start_variable


def load_states(case: Case, v: dict) -> list[cp.Constraint]:
    """First stage of the adjustable loads: off outside [alpha_d, beta_d], minimum operating time (17).
    Before the day every load is off, so a load on in hour 1 starts there."""
    z = v["z"]
    zs, cons = start_variable(z, np.zeros(len(case.loads)))
    return [*cons, cp.multiply(z, 1 - case.load_windows) == 0, *minimum_time(zs, z, case.load_array("min_up"))]


def load_dispatch(case: Case, ix: Index, v: dict) -> list[cp.Constraint]:
    """Dispatch of the adjustable loads: power limits (15) and energy within the window (16).

    Correction: (16) sums D dt over every sub-period of every hour in [alpha_d, beta_d] (the printed form sums
    over hours for each sub-period).
    """
    Dn = len(case.loads)
    Dl, z_n = v["D"], ix.expand(v["z"], Dn)
    return [
        Dl >= cp.multiply(ix.per_row(case.load_array("d_min")), z_n),  # (15)
        Dl <= cp.multiply(ix.per_row(case.load_array("d_max")), z_n),  # (15)
        cp.sum(Dl, axis=1) * ix.dt == np.repeat(case.load_array("energy"), ix.S),  # (16)
    ]
