"""The energy storage i in S: one mode at a time (10), minimum charging/discharging times (13)-(14), power by mode
(8)-(9) and stored energy (11)-(12)."""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from scenarios.case import Case

from .index import Index, hour_row, previous
from .states import minimum_time, start_variable


def storage_modes(case: Case, v: dict) -> list[cp.Constraint]:
    """First stage of the storage: one mode at a time (10) and minimum charging/discharging times (13)-(14).

    Correction: (13) binds the charging state v with the minimum charging time MC and (14) the discharging state
    u with MD (the printed equations swap them). Before the day the storage is idle (u = v = 0), so a mode held
    in hour 1 starts there and counts towards its minimum time (docs/model.md, "Conventions the paper leaves open").
    """
    st = case.storage
    u, vv = hour_row(v["u"]), hour_row(v["v"])
    us, cons_u = start_variable(u, np.zeros(1))
    vs, cons_v = start_variable(vv, np.zeros(1))
    return [
        *cons_u, *cons_v,
        v["u"] + v["v"] <= 1,  # (10)
        *minimum_time(vs, vv, np.array([st.min_charge])),  # (13)
        *minimum_time(us, u, np.array([st.min_discharge])),  # (14)
    ]


def storage_dispatch(case: Case, ix: Index, v: dict) -> list[cp.Constraint]:
    """Dispatch of the storage: power by mode (8)-(9) and stored energy (11)-(12).

    (11) runs continuously across hours from C_initial, and the end-of-day energy is at least C_initial so the
    day does not borrow from tomorrow. (12) is in the bounds of C (variables.py).
    """
    st = case.storage
    Pst, C = v["Pst"], v["C"]
    u_n, v_n = ix.expand(hour_row(v["u"]), 1), ix.expand(hour_row(v["v"]), 1)
    c_prev = previous(np.full(ix.S, st.c_initial), C)
    return [
        Pst <= st.p_dch_max * u_n - st.p_ch_min * v_n,  # (8)
        Pst >= st.p_dch_min * u_n - st.p_ch_max * v_n,  # (9)
        C == c_prev - Pst * ix.dt,  # (11)
        C[:, -1] >= st.c_initial,
    ]
