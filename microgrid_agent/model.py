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


def _transitions(y: cp.Expression, state: cp.Expression, initial: np.ndarray) -> list[cp.Constraint]:
    """Start indicators y_t = max(0, x_t - x_{t-1}) of an hourly 0/1 state x, exact for binary x.

    y >= x_t - x_{t-1}, y <= x_t and y <= 1 - x_{t-1} pin y to the positive part, so no later constraint can
    loosen a ramp or a minimum time by inflating y.
    """
    m = state.shape[0]
    before = cp.hstack([np.asarray(initial, float).reshape(m, 1), state[:, :-1]])
    return [y >= state - before, y <= state, y <= 1 - before]


def _starts(state: cp.Expression, initial: np.ndarray) -> tuple[cp.Variable, list[cp.Constraint]]:
    """A new start-indicator variable of an hourly state, with its defining constraints."""
    y = cp.Variable(state.shape, bounds=[0, 1])
    return y, _transitions(y, state, initial)


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


def _commitment(case: Case, v: dict) -> list[cp.Constraint]:
    """First stage of the units: start-up/shut-down indicators and minimum up/down times (6)-(7).

    Counters T^on/T^off are replaced by the tight linear form over start-up (y) and shut-down (w) indicators.
    """
    I, y, w = v["I"], v["y"], v["w"]
    initial = case.unit_array("initial_on")
    return [
        *_transitions(y, I, initial), *_transitions(w, 1 - I, 1 - initial),
        *_minimum_time(y, I, case.unit_array("min_up")),  # (6)
        *_minimum_time(w, 1 - I, case.unit_array("min_down")),  # (7)
    ]


def _units(case: Case, ix: _Index, v: dict) -> list[cp.Constraint]:
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
    p_prev = _previous(initial, P)
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


def _row(x: cp.Expression) -> cp.Expression:
    return cp.reshape(x, (1, HOURS), order="C")


def _storage_modes(case: Case, v: dict) -> list[cp.Constraint]:
    """First stage of the storage: one mode at a time (10) and minimum charging/discharging times (13)-(14).

    Correction: (13) binds the charging state v with the minimum charging time MC and (14) the discharging state
    u with MD (the printed equations swap them).
    """
    st = case.storage
    u, vv = _row(v["u"]), _row(v["v"])
    us, cons_u = _starts(u, np.zeros(1))
    vs, cons_v = _starts(vv, np.zeros(1))
    return [
        *cons_u, *cons_v,
        v["u"] + v["v"] <= 1,  # (10)
        *_minimum_time(vs, vv, np.array([st.min_charge])),  # (13)
        *_minimum_time(us, u, np.array([st.min_discharge])),  # (14)
    ]


def _storage(case: Case, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Dispatch of the storage: power by mode (8)-(9) and stored energy (11)-(12).

    (11) runs continuously across hours from C_initial, and the end-of-day energy is at least C_initial so the
    day does not borrow from tomorrow.
    """
    st = case.storage
    Pst, C = v["Pst"], v["C"]
    u_n, v_n = ix.expand(_row(v["u"]), 1), ix.expand(_row(v["v"]), 1)
    c_prev = _previous(np.full(ix.S, st.c_initial), C)
    return [
        Pst <= st.p_dch_max * u_n - st.p_ch_min * v_n,  # (8)
        Pst >= st.p_dch_min * u_n - st.p_ch_max * v_n,  # (9)
        C == c_prev - Pst * ix.dt,  # (11); (12) is in C's bounds
        C[:, -1] >= st.c_initial,
    ]


def _load_states(case: Case, v: dict) -> list[cp.Constraint]:
    """First stage of the adjustable loads: off outside [alpha_d, beta_d], minimum operating time (17)."""
    z = v["z"]
    zs, cons = _starts(z, np.zeros(len(case.loads)))
    return [*cons, cp.multiply(z, 1 - case.load_windows) == 0, *_minimum_time(zs, z, case.load_array("min_up"))]


def _loads(case: Case, ix: _Index, v: dict) -> list[cp.Constraint]:
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


def _balance(case: Case, scen: ScenarioSet, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Power balance (2) per scenario and sub-period, with renewables as used (availability minus spill).

    Load curtailment LS and renewable spill make every commitment feasible in every scenario. Scenario data
    (load, availability) enter only right-hand sides, so they may be cvxpy Parameters (decomposition.py).
    """
    supply = v["PM"] + v["LS"]
    demand = scen.load
    cons = []
    if case.units:
        supply = supply + ix.total(len(case.units)) @ v["P"]
    if case.renewables:
        R = len(case.renewables)
        supply = supply + ix.total(R) @ v["Pr"]
        cons.append(v["Pr"] <= _stacked(scen.renewable, R * ix.S, ix.N))
    if case.storage is not None:
        supply = supply + v["Pst"]
    if case.loads:
        demand = demand + ix.total(len(case.loads)) @ v["D"]
    return [supply == demand, *cons]


def _stacked(data, rows: int, n: int):
    """(M, S, N) scenario data as (M S, N) rows member-major; a Parameter already has that shape."""
    return data.reshape(rows, n) if isinstance(data, np.ndarray) else data


def _grid(case: Case, scen: ScenarioSet, params: Params, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Main grid transfer (18) and its positive mismatch (19)-(21).

    (18): islanded (U = 0) forces P_M = 0. The positive mismatch is modelled exactly as
    dP+ >= P_M - P^sch, dP+ >= 0 (minimised through its penalty); an infinite penalty becomes P_M <= P^sch
    wherever connected. ``mismatch="big-m"`` keeps the paper's indicator form (20)-(21), corrected so that it
    is exact (docs/model.md), to test that both give the same optimum.
    """
    p_sch = np.tile(np.repeat(params.p_sch, ix.K), (ix.S, 1))
    PM, dP, U = v["PM"], v["dP"], scen.connected
    pm_max = case.grid.p_m_max
    limits = [PM <= pm_max * U, PM >= -pm_max * U]  # (18)
    if np.isinf(params.penalty):
        # P_M <= P^sch where connected (U = 1) and no limit beyond (18) where islanded (U = 0).
        return [*limits, PM <= pm_max - cp.multiply(pm_max - p_sch, U), dP == 0]
    if params.mismatch == "positive-part":
        return [*limits, dP >= PM - p_sch]
    delta = v["delta"] = cp.Variable(PM.shape, boolean=True)
    M = case.grid.p_m_max + np.abs(p_sch)
    mismatch = PM - p_sch  # (19)
    return [
        *limits,
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
    pr = np.asarray(scen.probability, float)[:, None] * ew
    terms = {
        "generation": cp.sum(cp.multiply(np.tile(pr, (len(case.units), ix.N)) * ix.per_row(case.unit_array("cost")), v["P"])),
        "startup": startup_cost(case, v),
        "curtailment": cp.sum(cp.multiply(pr * case.grid.voll, v["LS"])),
        "penalty": cp.Constant(0.0),
    }
    if np.isfinite(params.penalty):
        terms["penalty"] = cp.sum(cp.multiply(pr * params.penalty, v["dP"]))
    if params.import_price is not None:
        terms["energy"] = cp.sum(cp.multiply(pr * np.repeat(params.import_price, ix.K), v["PM"]))
    return terms


def startup_cost(case: Case, v: dict) -> cp.Expression:
    """The first-stage part of F in (1): start-up and shut-down costs, once per transition."""
    return cp.sum(case.unit_array("startup_cost") @ v["y"] + case.unit_array("shutdown_cost") @ v["w"])


def _variables(case: Case, S: int, N: int, first_stage: str = "binary") -> dict[str, cp.Variable]:
    """The variables of S scenarios; first-stage ones are binary, or ``continuous`` in [0, 1] for a subproblem
    whose first stage the decomposition fixes through column bounds."""
    G, R, Dn = len(case.units), len(case.renewables), len(case.loads)
    kind = {"boolean": True} if first_stage == "binary" else {"bounds": [0, 1]}
    v = {
        "I": cp.Variable((G, HOURS), name="I", **kind),
        "y": cp.Variable((G, HOURS), bounds=[0, 1], name="y"),
        "w": cp.Variable((G, HOURS), bounds=[0, 1], name="w"),
        "P": cp.Variable((G * S, N), name="P"),
        "PM": cp.Variable((S, N), name="P_M"),
        "dP": cp.Variable((S, N), nonneg=True, name="dP_plus"),
        "LS": cp.Variable((S, N), nonneg=True, name="LS"),
    }
    if R:
        v["Pr"] = cp.Variable((R * S, N), nonneg=True, name="P_r")
    if case.storage is not None:
        v["u"] = cp.Variable(HOURS, name="u", **kind)
        v["v"] = cp.Variable(HOURS, name="v", **kind)
        v["Pst"] = cp.Variable((S, N), name="P_st")
        v["C"] = cp.Variable((S, N), bounds=[0, case.storage.c_max], name="C")
    if Dn:
        v["z"] = cp.Variable((Dn, HOURS), name="z", **kind)
        v["D"] = cp.Variable((Dn * S, N), name="D")
    return v


def _shutdown_after_ramping_down(case: Case, v: dict, dt: float) -> list[cp.Constraint]:
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


def first_stage_constraints(case: Case, v: dict, dt: float) -> list[cp.Constraint]:
    """The hourly decisions' own constraints: (6)-(7), (10), (13)-(14), the load windows and (17), and the
    shut-downs that ramps (5) at sub-period length ``dt`` (hours) allow."""
    cons = _commitment(case, v) + _shutdown_after_ramping_down(case, v, dt)
    if case.storage is not None:
        cons += _storage_modes(case, v)
    if case.loads:
        cons += _load_states(case, v)
    return cons


def second_stage_constraints(case: Case, scen, params: Params, ix: _Index, v: dict) -> list[cp.Constraint]:
    """Per scenario and sub-period: (2)-(5), (8)-(9), (11)-(12), (15)-(16), (18)-(21)."""
    cons = _units(case, ix, v) + _balance(case, scen, ix, v) + _grid(case, scen, params, ix, v)
    if case.storage is not None:
        cons += _storage(case, ix, v)
    if case.loads:
        cons += _loads(case, ix, v)
    return cons


def build(case: Case, scen: ScenarioSet, params: Params, fixed: dict[str, np.ndarray] | None = None,
          pinned: tuple[int, dict[str, np.ndarray]] | None = None) -> Model:
    """Build objective (1) s.t. (2)-(21) for the scenario set.

    ``fixed`` pins first-stage variables by name (``I``, ``u``, ``v``, ``z``), e.g. to evaluate a given commitment
    (VSS, brute force). ``pinned = (n0, values)`` pins second-stage variables (``P``, ``Pst``, ``D``...) in the
    sub-periods before n0 to values of their full shape: the past of a day being operated (realtime.py).
    """
    ix = _Index(scen.S, scen.subperiods)
    v = _variables(case, scen.S, ix.N)
    cons = first_stage_constraints(case, v, ix.dt) + second_stage_constraints(case, scen, params, ix, v)
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
