"""The stochastic market-based schedule as one cvxpy MILP: objective (1) and constraints (2)-(21), vectorised.

Every constraint family is one array expression over (component x scenario, sub-period); there are no Python
loops over scenarios or sub-periods. Second-stage variables of a family with several members (units, loads,
renewables) are stacked member-major, row ``m * S + s``. First-stage (hourly) variables enter the sub-period
rows through constant expansion matrices. docs/model.md maps each equation to the function that builds it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from scenarios.case import HOURS, Case
from scenarios.generation import ScenarioSet

from .schedule import energy_weight

Mismatch = Literal["positive-part", "big-m"]


@dataclass(frozen=True)
class Params:
    """What a solve varies around the case: the award P^sch (24,), the penalty c, the cost convention."""

    p_sch: np.ndarray
    penalty: float
    cost_convention: str = "real"
    mismatch: Mismatch = "positive-part"
    import_price: np.ndarray | None = None  # (24,) $/MWh paid for P_M, for bidding (microgrid_agent/bidding.py)


@dataclass
class Model:
    """The built problem and its variables, for the solver and the result extraction."""

    problem: cp.Problem
    var: dict[str, cp.Variable]
    case: Case
    scen: ScenarioSet
    params: Params
    terms: dict[str, cp.Expression]


class _Index:
    """Constant matrices that map hourly first-stage variables onto stacked (member x scenario, sub-period) rows."""

    def __init__(self, S: int, K: int):
        self.S, self.K, self.N = S, K, HOURS * K
        self.dt = 1.0 / K
        # E (24, N): hour t -> its K sub-periods; E_first (24, N): hour t -> its first sub-period only.
        self.E = sp.kron(sp.eye(HOURS), np.ones((1, K)), format="csr")
        self.E_first = sp.csr_matrix((np.ones(HOURS), (np.arange(HOURS), np.arange(HOURS) * K)), shape=(HOURS, self.N))

    def rows(self, m: int) -> sp.csr_matrix:
        """(m S, m): copies each of m members' hourly row to its S scenario rows."""
        return sp.kron(sp.eye(m), np.ones((self.S, 1)), format="csr")

    def total(self, m: int) -> sp.csr_matrix:
        """(S, m S): sums m members' rows per scenario."""
        return sp.kron(np.ones((1, m)), sp.eye(self.S), format="csr")

    def expand(self, hourly: cp.Expression, m: int) -> cp.Expression:
        """(m, 24) hourly variable -> (m S, N) sub-period rows."""
        return self.rows(m) @ hourly @ self.E

    def at_hour_start(self, hourly: cp.Expression, m: int) -> cp.Expression:
        """(m, 24) -> (m S, N), nonzero only in the first sub-period of each hour."""
        return self.rows(m) @ hourly @ self.E_first

    def per_row(self, values: np.ndarray) -> np.ndarray:
        """(m,) member constants -> (m S, N) array."""
        return np.repeat(np.asarray(values, float), self.S)[:, None] * np.ones((1, self.N))


def _previous(first: np.ndarray | cp.Expression, x: cp.Expression) -> cp.Expression:
    """x shifted one sub-period later along axis 1, with ``first`` (rows,) as the value before the day."""
    return cp.hstack([cp.reshape(first, (x.shape[0], 1), order="C"), x[:, :-1]])


def _window(length: int) -> np.ndarray:
    """(24, 24) W with W[t, k] = 1 for t - length < k <= t: sums over the last ``length`` hours."""
    t = np.arange(HOURS)
    return ((t[None, :] <= t[:, None]) & (t[None, :] > t[:, None] - length)).astype(float)


def _transitions(state: cp.Variable, initial: np.ndarray) -> tuple[cp.Expression, list[cp.Constraint]]:
    """Start-up indicators y_t = max(0, x_t - x_{t-1}) of an hourly 0/1 state, exact for binary x.

    y >= x_t - x_{t-1}, y <= x_t and y <= 1 - x_{t-1} pin y to the positive part, so no later constraint can
    loosen a ramp or a minimum time by inflating y.
    """
    m = state.shape[0]
    before = cp.hstack([np.asarray(initial, float).reshape(m, 1), state[:, :-1]])
    y = cp.Variable(state.shape, bounds=[0, 1])
    return y, [y >= state - before, y <= state, y <= 1 - before]


def _minimum_time(starts: cp.Expression, state: cp.Expression, lengths: np.ndarray) -> list[cp.Constraint]:
    """Tight minimum-time form: the starts within the last L hours may not exceed the state now.

    Used for minimum up time (6) with (starts, state) = (y, I), minimum down time (7) with (w, 1 - I), the
    corrected minimum charge/discharge times (13)-(14) and the minimum operating time of loads (17). It is the
    Rajan-Takriti formulation, which describes the convex hull of one unit's up/down polytope.
    """
    groups = {}
    for row, length in enumerate(lengths):
        groups.setdefault(int(length), []).append(row)
    out = []
    for length, rows in groups.items():
        if length > 1:
            out.append(starts[rows, :] @ _window(length).T <= state[rows, :])
    return out


def _units(case: Case, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Dispatchable units: limits (3), ramps (4)-(5), minimum up/down times (6)-(7).

    Departures from the printed form (docs/model.md): ramps hold between every pair of consecutive sub-periods,
    across hour boundaries too, as rates UR dt per sub-period, and allow a start-up (shut-down) to jump from
    (to) zero through the minimum output in one step; (6)-(7) use start-up/shut-down indicators in the tight
    linear form instead of counters T^on/T^off.
    """
    G = len(case.units)
    I, P = v["I"], v["P"]
    p_min, p_max = case.unit_array("p_min"), case.unit_array("p_max")
    initial = case.unit_array("initial_on")
    y, cons_y = _transitions(I, initial)
    w, cons_w = _transitions(1 - I, 1 - initial)
    v["y"], v["w"] = y, w
    I_n = ix.expand(I, G)
    p_prev = _previous(np.repeat(p_min * initial, ix.S), P)
    allowance = cp.multiply(ix.per_row(p_min), ix.at_hour_start(y, G))
    allowance_down = cp.multiply(ix.per_row(p_min), ix.at_hour_start(w, G))
    return [
        *cons_y, *cons_w,
        P >= cp.multiply(ix.per_row(p_min), I_n),  # (3)
        P <= cp.multiply(ix.per_row(p_max), I_n),  # (3)
        P - p_prev <= ix.per_row(case.unit_array("ramp_up") * ix.dt) + allowance,  # (4)
        p_prev - P <= ix.per_row(case.unit_array("ramp_down") * ix.dt) + allowance_down,  # (5)
        *_minimum_time(y, I, case.unit_array("min_up")),  # (6)
        *_minimum_time(w, 1 - I, case.unit_array("min_down")),  # (7)
    ]


def _storage(case: Case, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Energy storage: power by mode (8)-(9), one mode at a time (10), energy (11)-(12), mode times (13)-(14).

    Corrections: (13) binds the charging state v with the minimum charging time MC and (14) the discharging
    state u with MD (the printed equations swap them); (11) runs continuously across hours from C_initial,
    and the end-of-day energy is at least C_initial so the day does not borrow from tomorrow.
    """
    st = case.storage
    u, vv, Pst, C = v["u"], v["v"], v["Pst"], v["C"]
    u_n, v_n = ix.expand(cp.reshape(u, (1, HOURS), order="C"), 1), ix.expand(cp.reshape(vv, (1, HOURS), order="C"), 1)
    us, cons_u = _transitions(cp.reshape(u, (1, HOURS), order="C"), np.zeros(1))
    vs, cons_v = _transitions(cp.reshape(vv, (1, HOURS), order="C"), np.zeros(1))
    c_prev = _previous(np.full(ix.S, st.c_initial), C)
    return [
        *cons_u, *cons_v,
        Pst <= st.p_dch_max * u_n - st.p_ch_min * v_n,  # (8)
        Pst >= st.p_dch_min * u_n - st.p_ch_max * v_n,  # (9)
        u + vv <= 1,  # (10)
        C == c_prev - Pst * ix.dt,  # (11); (12) is in C's bounds
        C[:, -1] >= st.c_initial,
        *_minimum_time(vs, cp.reshape(vv, (1, HOURS), order="C"), np.array([st.min_charge])),  # (13)
        *_minimum_time(us, cp.reshape(u, (1, HOURS), order="C"), np.array([st.min_discharge])),  # (14)
    ]


def _loads(case: Case, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Adjustable loads: power limits (15), energy within the window (16), minimum operating time (17).

    Correction: (16) sums D dt over every sub-period of every hour in [alpha_d, beta_d] (the printed form sums
    over hours for each sub-period). A load is off outside its window.
    """
    Dn = len(case.loads)
    z, Dl = v["z"], v["D"]
    z_n = ix.expand(z, Dn)
    zs, cons = _transitions(z, np.zeros(Dn))
    return [
        *cons,
        cp.multiply(z, 1 - case.load_windows) == 0,
        Dl >= cp.multiply(ix.per_row(case.load_array("d_min")), z_n),  # (15)
        Dl <= cp.multiply(ix.per_row(case.load_array("d_max")), z_n),  # (15)
        cp.sum(Dl, axis=1) * ix.dt == np.repeat(case.load_array("energy"), ix.S),  # (16)
        *_minimum_time(zs, z, case.load_array("min_up")),  # (17)
    ]


def _balance(case: Case, scen: ScenarioSet, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Power balance (2) per scenario and sub-period, with renewables as used (availability minus spill).

    Load curtailment LS and renewable spill make every commitment feasible in every scenario.
    """
    supply = v["PM"] + v["LS"]
    demand = scen.load
    if case.units:
        supply = supply + ix.total(len(case.units)) @ v["P"]
    if case.renewables:
        supply = supply + ix.total(len(case.renewables)) @ v["Pr"]
    if case.storage is not None:
        supply = supply + v["Pst"]
    if case.loads:
        demand = demand + ix.total(len(case.loads)) @ v["D"]
    return [supply == demand]


def _grid(case: Case, scen: ScenarioSet, params: Params, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Main grid transfer (18) and its positive mismatch (19)-(21).

    (18) is in P_M's bounds: islanded (U = 0) forces P_M = 0. The positive mismatch is modelled exactly as
    dP+ >= P_M - P^sch, dP+ >= 0 (minimised through its penalty); an infinite penalty becomes P_M <= P^sch
    wherever connected. ``mismatch="big-m"`` keeps the paper's indicator form (20)-(21), corrected so that it
    is exact (docs/model.md), to test that both give the same optimum.
    """
    p_sch = np.tile(np.repeat(params.p_sch, ix.K), (ix.S, 1))
    PM, dP = v["PM"], v["dP"]
    if np.isinf(params.penalty):
        return [PM <= np.where(scen.connected > 0, p_sch, case.grid.p_m_max), dP == 0]
    if params.mismatch == "positive-part":
        return [dP >= PM - p_sch]
    delta = v["delta"] = cp.Variable(PM.shape, boolean=True)
    M = case.grid.p_m_max + np.abs(p_sch)
    mismatch = PM - p_sch  # (19)
    return [
        dP <= cp.multiply(M, delta),  # (20), with dP+ >= 0 in its bounds
        mismatch - dP <= cp.multiply(M, 1 - delta),  # (21)
        mismatch - dP >= -cp.multiply(M, 1 - delta),  # (21)
        mismatch <= cp.multiply(M, delta),  # delta = 0 only where the mismatch is not positive
    ]


def _objective(case: Case, scen: ScenarioSet, params: Params, ix: _Index, v: dict) -> dict[str, cp.Expression]:
    """Objective (1) by term: expected generation, start-up/shut-down, curtailment and penalty cost.

    Energy terms are MW x ``energy_weight`` (dt in the real convention); start-up and shut-down costs are
    counted once per transition, as part of F.
    """
    ew = energy_weight(ix.K, params.cost_convention)
    pr = scen.probability[:, None] * ew
    terms = {
        "generation": cp.sum(cp.multiply(np.tile(pr, (len(case.units), ix.N)) * ix.per_row(case.unit_array("cost")), v["P"])),
        "startup": cp.sum(case.unit_array("startup_cost") @ v["y"] + case.unit_array("shutdown_cost") @ v["w"]),
        "curtailment": cp.sum(cp.multiply(pr * case.grid.voll, v["LS"])),
        "penalty": cp.Constant(0.0),
    }
    if np.isfinite(params.penalty):
        terms["penalty"] = cp.sum(cp.multiply(pr * params.penalty, v["dP"]))
    if params.import_price is not None:
        terms["energy"] = cp.sum(cp.multiply(pr * np.repeat(params.import_price, ix.K), v["PM"]))
    return terms


def _variables(case: Case, scen: ScenarioSet, ix: _Index) -> dict[str, cp.Variable]:
    S, N = scen.S, ix.N
    G, R, Dn = len(case.units), len(case.renewables), len(case.loads)
    pm_max = case.grid.p_m_max * scen.connected
    v = {
        "I": cp.Variable((G, HOURS), boolean=True, name="I"),
        "P": cp.Variable((G * S, N), name="P"),
        "PM": cp.Variable((S, N), bounds=[-pm_max, pm_max], name="P_M"),
        "dP": cp.Variable((S, N), nonneg=True, name="dP_plus"),
        "LS": cp.Variable((S, N), nonneg=True, name="LS"),
    }
    if R:
        v["Pr"] = cp.Variable((R * S, N), bounds=[0, scen.renewable.reshape(R * S, N)], name="P_r")
    if case.storage is not None:
        v["u"] = cp.Variable(HOURS, boolean=True, name="u")
        v["v"] = cp.Variable(HOURS, boolean=True, name="v")
        v["Pst"] = cp.Variable((S, N), name="P_st")
        v["C"] = cp.Variable((S, N), bounds=[0, case.storage.c_max], name="C")
    if Dn:
        v["z"] = cp.Variable((Dn, HOURS), boolean=True, name="z")
        v["D"] = cp.Variable((Dn * S, N), name="D")
    return v


def build(case: Case, scen: ScenarioSet, params: Params, fixed: dict[str, np.ndarray] | None = None,
          pinned: tuple[int, dict[str, np.ndarray]] | None = None) -> Model:
    """Build objective (1) s.t. (2)-(21) for the scenario set.

    ``fixed`` pins first-stage variables by name (``I``, ``u``, ``v``, ``z``), e.g. to evaluate a given commitment
    (VSS, brute force). ``pinned = (n0, values)`` pins second-stage variables (``P``, ``Pst``, ``D``...) in the
    sub-periods before n0 to values of their full shape: the past of a day being operated (realtime.py).
    """
    ix = _Index(scen.S, scen.subperiods)
    v = _variables(case, scen, ix)
    cons = _units(case, ix, v) + _balance(case, scen, ix, v) + _grid(case, scen, params, ix, v)
    if case.storage is not None:
        cons += _storage(case, ix, v)
    if case.loads:
        cons += _loads(case, ix, v)
    for name, value in (fixed or {}).items():
        if name in v:
            cons.append(v[name] == np.asarray(value, float).reshape(v[name].shape))
    if pinned is not None and pinned[0] > 0:
        n0, values = pinned
        cons += [v[name][:, :n0] == np.asarray(value, float).reshape(v[name].shape)[:, :n0]
                 for name, value in values.items() if name in v]
    terms = _objective(case, scen, params, ix, v)
    problem = cp.Problem(cp.Minimize(sum(terms.values())), cons)
    return Model(problem, v, case, scen, params, terms)
