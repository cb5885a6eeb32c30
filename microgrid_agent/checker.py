"""Independent checker of a stochastic schedule: verifies (2)-(21) in every scenario and recomputes cost (1).

A separate code path from the model on purpose: plain numpy over the arrays of the result contract
(``microgrid_agent.schedule``), written from the paper and docs/model.md, never importing the model. A bug would
have to be made twice, the same way, to pass unseen. Each family of constraints is one vectorised comparison over
(element, scenario, sub-period); only the few reported violations are formatted one by one.

Conventions checked (the contract the model implements, the corrections of docs/model.md included):
sub-period n = (t-1)K + tau - 1, hour t = n // K + 1; ramps (4)-(5) between consecutive sub-periods across hours,
with a start-up/shut-down allowance of P_min at the first sub-period of an hour; minimum times (6)-(7), (13)-(14)
and (17) in the Rajan-Takriti form over start indicators, with (13) binding charging v and (14) discharging u;
state of charge (11) continuing from C_initial with an end-of-day floor of C_initial; dP+ of (19)-(21) the exact
positive part of P_M - P_sch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scenarios.case import Case
from scenarios.generation import ScenarioSet
from scenarios.horizon import HOURS, per_subperiod, subperiod_hours

from .schedule import CostBreakdown, StochasticSchedule, energy_weight, start_indicators

MAX_MESSAGES = 50
PER_CHECK = 8  # so one badly broken family cannot hide the others from the first lines of the report
OBJECTIVE_RTOL = 1e-6
OBJECTIVE_ATOL = 1e-3


class ScheduleCheckError(AssertionError):
    """A schedule that breaks a constraint or misstates its cost."""


@dataclass(frozen=True)
class CheckReport:
    """What the checker found. ``violations`` holds at most ``MAX_MESSAGES`` lines; ``count`` counts them all."""

    violations: tuple[str, ...]
    count: int
    cost: CostBreakdown
    objective: float

    @property
    def ok(self) -> bool:
        return self.count == 0

    def summary(self, lines: int = 10) -> str:
        if self.ok:
            return f"schedule ok, objective {self.objective:.6g}"
        head = [f"schedule check failed: {self.count} violation(s); first {min(lines, len(self.violations))}:"]
        return "\n".join(head + [f"  {v}" for v in self.violations[:lines]])

    def raise_if_failed(self, lines: int = 10) -> None:
        if not self.ok:
            raise ScheduleCheckError(self.summary(lines))


class _Findings:
    """Collects violations: counts every offending element, formats only the first few."""

    def __init__(self, case: Case, subperiods: int, tol: float):
        self.tol = tol
        self.k = max(int(subperiods), 1)
        self.messages: list[str] = []
        self.count = 0
        self.names = {
            "unit": [u.name for u in case.units],
            "renewable": [r.name for r in case.renewables],
            "load": [d.name for d in case.loads],
        }

    def _label(self, axis: str, i: int) -> str:
        if axis in self.names:
            names = self.names[axis]
            return f"{axis} {names[i] if i < len(names) else i}"
        if axis == "scenario":
            return f"scenario {i}"
        if axis == "hour":
            return f"hour {i + 1}"
        if axis == "sub":
            return f"hour {i // self.k + 1} sub-period {i % self.k + 1}"
        return f"{axis} {i}"

    def note(self, message: str, count: int = 1) -> None:
        self.count += count
        if len(self.messages) < MAX_MESSAGES:
            self.messages.append(message)

    def flag(self, eq: str, what: str, excess, axes: tuple[str, ...], scale=1.0) -> None:
        """Report every element where ``excess`` (the amount by which a constraint is broken) exceeds tolerance.

        ``scale`` widens the tolerance to tol * max(1, |scale|) for equalities over large or summed quantities.
        """
        excess = np.asarray(excess, dtype=float)
        bad = excess > self.tol * np.maximum(1.0, np.abs(np.asarray(scale, dtype=float)))
        n = int(np.count_nonzero(bad))
        if n == 0:
            return
        self.count += n
        excess = np.broadcast_to(excess, bad.shape)
        room = min(PER_CHECK, MAX_MESSAGES - len(self.messages))
        for idx in np.argwhere(bad)[: max(room, 0)]:
            where = ", ".join(self._label(a, int(i)) for a, i in zip(axes, idx))
            self.messages.append(f"({eq}) {what}: {where}: violated by {excess[tuple(idx)]:.6g}")
        if n > room > 0 and len(self.messages) < MAX_MESSAGES:
            self.messages.append(f"({eq}) {what}: {n - room} more element(s) not listed")


def _recent(starts: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Sum of ``starts`` over hours max(1, t-L+1)..t, per row with its own L: the Rajan-Takriti left-hand side."""
    cum = np.concatenate([np.zeros((starts.shape[0], 1)), np.cumsum(starts, axis=1)], axis=1)
    lo = np.maximum(0, np.arange(HOURS)[None, :] + 1 - length.astype(int)[:, None])
    return cum[:, 1:] - np.take_along_axis(cum, lo, axis=1)


def _binary(f: _Findings, eq: str, name: str, x: np.ndarray, axes: tuple[str, ...]) -> np.ndarray:
    """Flag values not 0/1 within tolerance; return the rounded 0/1 array the logical checks then use."""
    f.flag(eq, f"{name} not binary", np.minimum(np.abs(x), np.abs(x - 1.0)), axes)
    return (x > 0.5).astype(float)


def _expected_shapes(case: Case, scen: ScenarioSet) -> dict[str, tuple[int, ...]]:
    g, r, d = len(case.units), len(case.renewables), len(case.loads)
    s, n = len(np.atleast_1d(scen.probability)), HOURS * scen.subperiods
    return {
        "scenarios.probability": (s,), "scenarios.load": (s, n), "scenarios.renewable": (r, s, n),
        "scenarios.connected": (s, n), "schedule.probability": (s,),
        "first.commitment": (g, HOURS), "first.startup": (g, HOURS), "first.shutdown": (g, HOURS),
        "first.discharging": (HOURS,), "first.charging": (HOURS,), "first.load_on": (d, HOURS),
        "dispatch.p_unit": (g, s, n), "dispatch.p_renewable": (r, s, n), "dispatch.p_storage": (s, n),
        "dispatch.soc": (s, n), "dispatch.d_load": (d, s, n), "dispatch.p_m": (s, n),
        "dispatch.load_shed": (s, n), "dispatch.dp_plus": (s, n), "p_sch": (HOURS,),
    }


def _arrays(scen: ScenarioSet, schedule: StochasticSchedule, p_sch) -> dict[str, np.ndarray]:
    out = {f"scenarios.{k}": getattr(scen, k) for k in ("probability", "load", "renewable", "connected")}
    out["schedule.probability"] = schedule.probability
    for part, obj in (("first", schedule.first), ("dispatch", schedule.dispatch)):
        out |= {f"{part}.{k}": getattr(obj, k) for k in obj.__dataclass_fields__}
    out["p_sch"] = p_sch
    return {k: np.asarray(v, dtype=float) for k, v in out.items()}


def _check_inputs(f: _Findings, case: Case, scen: ScenarioSet, schedule: StochasticSchedule, a: dict) -> bool:
    """Shapes, finiteness, names, probabilities. False when the arrays cannot be checked further."""
    if schedule.subperiods != scen.subperiods:
        f.note(f"shape: schedule has {schedule.subperiods} sub-periods per hour, scenarios {scen.subperiods}")
        return False
    expected = _expected_shapes(case, scen)
    shapes_ok = True
    for key, shape in expected.items():
        if a[key].shape != shape:
            f.note(f"shape: {key} is {a[key].shape}, expected {shape}")
            shapes_ok = False
    if not shapes_ok:
        return False
    for key, arr in a.items():
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            f.note(f"value: {key} has {bad} NaN or infinite value(s)", bad)
    if tuple(schedule.unit_names) != tuple(f.names["unit"]):
        f.note(f"names: schedule units {tuple(schedule.unit_names)} != case units {tuple(f.names['unit'])}")
    if tuple(schedule.load_names) != tuple(f.names["load"]):
        f.note(f"names: schedule loads {tuple(schedule.load_names)} != case loads {tuple(f.names['load'])}")
    pr = a["scenarios.probability"]
    f.flag("1", "scenario probability negative", -pr, ("scenario",))
    if not abs(pr.sum() - 1.0) <= f.tol:
        f.note(f"(1) scenario probabilities sum to {pr.sum():.9g}, not 1")
    f.flag("1", "schedule probability differs from the scenario set's",
           np.abs(a["schedule.probability"] - pr), ("scenario",))
    conn = a["scenarios.connected"]
    f.flag("18", "scenario connection status U not 0/1", np.minimum(np.abs(conn), np.abs(conn - 1)),
           ("scenario", "sub"))
    return True


def _check_units(f: _Findings, case: Case, a: dict, k: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Commitment logic, limits (3), ramps (4)-(5), minimum up/down (6)-(7). Returns the true start-ups/shut-downs."""
    ug = ("unit", "hour")
    commit = _binary(f, "3", "commitment I", a["first.commitment"], ug)
    _binary(f, "6", "start-up y", a["first.startup"], ug)
    _binary(f, "7", "shut-down w", a["first.shutdown"], ug)
    initial = case.unit_array("initial_on")
    up = start_indicators(commit, initial)
    down = start_indicators(1.0 - commit, 1.0 - initial)
    f.flag("6", "start-up y != max(0, I_t - I_t-1)", np.abs(a["first.startup"] - up), ug)
    f.flag("7", "shut-down w != max(0, I_t-1 - I_t)", np.abs(a["first.shutdown"] - down), ug)

    p = a["dispatch.p_unit"]  # (G, S, N)
    p_min, p_max = case.unit_array("p_min")[:, None, None], case.unit_array("p_max")[:, None, None]
    on = per_subperiod(commit, k)[:, None, :]
    f.flag("3", "output below P_min I", p_min * on - p, ("unit", "scenario", "sub"))
    f.flag("3", "output above P_max I", p - p_max * on, ("unit", "scenario", "sub"))

    first_sub = (np.arange(HOURS * k) % k == 0).astype(float)
    start_allow = p_min * (per_subperiod(up, k) * first_sub)[:, None, :]
    stop_allow = p_min * (per_subperiod(down, k) * first_sub)[:, None, :]
    # a unit on at midnight may shut down from its initial output in the first step
    stop_allow[:, :, 0] = case.unit_array("initial_output")[:, None] * down[:, :1]
    before = np.broadcast_to(case.unit_array("initial_output")[:, None, None], (p.shape[0], p.shape[1], 1))
    prev = np.concatenate([before, p[:, :, :-1]], axis=2)
    ramp_up = case.unit_array("ramp_up")[:, None, None] * dt
    ramp_down = case.unit_array("ramp_down")[:, None, None] * dt
    f.flag("4", "ramp-up limit", (p - prev) - (ramp_up + start_allow), ("unit", "scenario", "sub"))
    f.flag("5", "ramp-down limit", (prev - p) - (ramp_down + stop_allow), ("unit", "scenario", "sub"))

    f.flag("6", "minimum up time", _recent(up, case.unit_array("min_up")) - commit, ug)
    f.flag("7", "minimum down time", _recent(down, case.unit_array("min_down")) - (1.0 - commit), ug)
    # across midnight: min_up (on) or min_down (off) minus the hours already spent in the initial state
    keep = case.unit_array("min_up") * initial + case.unit_array("min_down") * (1.0 - initial)
    spent = np.array([u.initial_hours or HOURS for u in case.units], dtype=float)
    owed = (np.arange(HOURS)[None, :] < (keep - spent)[:, None])
    f.flag("6", "unit left its initial state before its minimum time since", owed * np.abs(commit - initial[:, None]),
           ug)
    return up, down


def _check_storage(f: _Findings, case: Case, a: dict, k: int, dt: float) -> None:
    """Storage (8)-(14), with (13) binding charging v and (14) discharging u (docs/model.md)."""
    p, soc = a["dispatch.p_storage"], a["dispatch.soc"]
    ch = _binary(f, "10", "charging v", a["first.charging"], ("hour",))
    dch = _binary(f, "10", "discharging u", a["first.discharging"], ("hour",))
    es = case.storage
    if es is None:
        f.flag("8", "storage power without storage in the case", np.abs(p), ("scenario", "sub"))
        return
    tag = f"storage {es.name}"
    f.flag("10", f"{tag} charging and discharging in the same hour", ch + dch - 1.0, ("hour",))
    u, v = per_subperiod(dch, k)[None, :], per_subperiod(ch, k)[None, :]
    f.flag("8", f"{tag} power above P_dch_max u - P_ch_min v", p - (es.p_dch_max * u - es.p_ch_min * v),
           ("scenario", "sub"))
    f.flag("9", f"{tag} power below P_dch_min u - P_ch_max v", (es.p_dch_min * u - es.p_ch_max * v) - p,
           ("scenario", "sub"))
    prev = np.concatenate([np.full((soc.shape[0], 1), es.c_initial), soc[:, :-1]], axis=1)
    f.flag("11", f"{tag} state of charge C != C_prev - P dt", np.abs(soc - (prev - p * dt)), ("scenario", "sub"),
           scale=es.c_max)
    f.flag("12", f"{tag} state of charge below 0", -soc, ("scenario", "sub"))
    f.flag("12", f"{tag} state of charge above C_max", soc - es.c_max, ("scenario", "sub"))
    f.flag("12", f"{tag} end-of-day state of charge below C_initial", es.c_initial - soc[:, -1], ("scenario",))
    none = np.zeros(1)
    f.flag("13", f"{tag} minimum charging time",
           _recent(start_indicators(ch[None, :], none), np.array([es.min_charge]))[0] - ch, ("hour",))
    f.flag("14", f"{tag} minimum discharging time",
           _recent(start_indicators(dch[None, :], none), np.array([es.min_discharge]))[0] - dch, ("hour",))


def _check_loads(f: _Findings, case: Case, a: dict, k: int, dt: float) -> None:
    """Adjustable loads (15)-(17): power limits, energy over the window's sub-periods, minimum operating time."""
    dh = ("load", "hour")
    z = _binary(f, "15", "load state z", a["first.load_on"], dh)
    window = case.load_windows
    f.flag("16", "load on outside its window [alpha, beta]", z * (1.0 - window), dh)
    d = a["dispatch.d_load"]  # (D, S, N)
    on = per_subperiod(z, k)[:, None, :]
    f.flag("15", "load below D_min z", case.load_array("d_min")[:, None, None] * on - d, ("load", "scenario", "sub"))
    f.flag("15", "load above D_max z", d - case.load_array("d_max")[:, None, None] * on, ("load", "scenario", "sub"))
    energy = (d * per_subperiod(window, k)[:, None, :]).sum(axis=2) * dt
    required = case.load_array("energy")[:, None]
    f.flag("16", "energy in window != E_d", np.abs(energy - required), ("load", "scenario"), scale=required)
    f.flag("17", "minimum operating time",
           _recent(start_indicators(z, np.zeros(len(z))), case.load_array("min_up")) - z, dh)


def _check_balance_and_grid(f: _Findings, case: Case, a: dict, k: int, p_sch: np.ndarray,
                            penalty: float) -> np.ndarray:
    """Balance (2), renewables, grid limit (18), mismatch (19)-(21). Returns the true positive mismatch (S, N)."""
    sn = ("scenario", "sub")
    load, avail, conn = a["scenarios.load"], a["scenarios.renewable"], a["scenarios.connected"]
    ren, p_st, d = a["dispatch.p_renewable"], a["dispatch.p_storage"], a["dispatch.d_load"]
    p_m, shed, dp = a["dispatch.p_m"], a["dispatch.load_shed"], a["dispatch.dp_plus"]

    demand = load + d.sum(axis=0)
    supply = a["dispatch.p_unit"].sum(axis=0) + ren.sum(axis=0) + p_st + p_m + shed
    f.flag("2", "power balance", np.abs(supply - demand), sn, scale=demand)
    f.flag("2", "load shed negative", -shed, sn)
    f.flag("2", "load shed above demand", shed - (demand + np.maximum(0.0, -p_st)), sn)
    f.flag("2", "renewable output negative", -ren, ("renewable", "scenario", "sub"))
    f.flag("2", "renewable output above availability", ren - avail, ("renewable", "scenario", "sub"))

    limit = case.grid.p_m_max * conn
    f.flag("18", "grid transfer above P_M_max U", p_m - limit, sn)
    f.flag("18", "grid transfer below -P_M_max U", -limit - p_m, sn)

    sch = per_subperiod(p_sch, k)[None, :]
    positive = np.maximum(0.0, p_m - sch)
    if math.isinf(penalty):
        # No mismatch may be bought at an infinite price: P_M <= P_sch wherever connected. Islanded with a
        # negative award the shortfall is forced, so there dP+ may be anything between 0 and its positive part.
        f.flag("19", "infinite penalty: grid transfer above P_sch", (p_m - sch) * conn, sn)
        f.flag("19", "dP+ != max(0, P_M - P_sch)", np.abs(dp - positive) * conn, sn)
        f.flag("19", "dP+ outside [0, max(0, P_M - P_sch)]",
               np.maximum(-dp, dp - positive) * (1.0 - conn), sn)
        return np.zeros_like(positive)
    f.flag("19", "dP+ != max(0, P_M - P_sch)", np.abs(dp - positive), sn)
    return positive


def _cost(case: Case, a: dict, up: np.ndarray, down: np.ndarray, mismatch: np.ndarray, penalty: float,
          weight: float, import_price, shortfall: np.ndarray | None) -> CostBreakdown:
    """Objective (1): expected generation, curtailment and mismatch energy cost, plus first-stage start-up cost;
    with ``shortfall`` (S, N), the award not taken where it must be, at VOLL in the penalty."""
    pr = a["scenarios.probability"]
    generation = weight * float(np.einsum("g,gsn,s->", case.unit_array("cost"), a["dispatch.p_unit"], pr))
    startup = float((case.unit_array("startup_cost")[:, None] * up).sum()
                    + (case.unit_array("shutdown_cost")[:, None] * down).sum())
    curtailment = weight * case.grid.voll * float(pr @ a["dispatch.load_shed"].sum(axis=1))
    mismatch_cost = 0.0 if math.isinf(penalty) else weight * penalty * float(pr @ mismatch.sum(axis=1))
    if shortfall is not None:
        mismatch_cost += weight * case.grid.voll * float(pr @ shortfall.sum(axis=1))
    energy = 0.0
    if import_price is not None:
        price = per_subperiod(np.asarray(import_price, float), a["dispatch.p_m"].shape[1] // HOURS)
        energy = weight * float(pr @ (a["dispatch.p_m"] * price).sum(axis=1))
    return CostBreakdown(generation=generation, startup=startup, curtailment=curtailment, penalty=mismatch_cost,
                         energy=energy)


def _close(x: float, y: float) -> bool:
    return abs(x - y) <= OBJECTIVE_RTOL * max(abs(x), abs(y)) + OBJECTIVE_ATOL


def check_schedule(case: Case, scenarios: ScenarioSet, schedule: StochasticSchedule, p_sch=None,
                   penalty: float | None = None, tol: float = 1e-5, import_price=None,
                   deviation_cost=None, take_award: bool | None = None) -> CheckReport:
    """Verify every constraint of ``schedule`` in every scenario and recompute its expected cost.

    ``p_sch`` (24,) defaults to the case's award, ``penalty`` to the schedule's (``inf`` forbids any positive
    mismatch). Violations beyond ``tol`` (widened to tol x magnitude for balance, energy and state of charge) are
    reported by equation number; the recomputed objective must match ``schedule.objective``. ``import_price``
    (24,) $/MWh prices P_M, as the bidding model does. ``deviation_cost`` (a rule's hourly pieces, with ``slope``
    and ``intercept`` (24, J)) prices the mismatch instead of ``penalty``: max_j slope_j d + intercept_j per
    sub-period, d = P_M - P_sch. ``take_award`` (default: the schedule's) prices the award not taken while
    connected, max(0, U P_sch - P_M), at VOLL.
    """
    p_sch = case.grid.p_sch if p_sch is None else p_sch
    penalty = float(schedule.penalty if penalty is None else penalty)
    k = int(scenarios.subperiods)
    f = _Findings(case, k, tol)
    nan_cost = CostBreakdown(math.nan, math.nan, math.nan, math.nan)

    a = _arrays(scenarios, schedule, p_sch)
    if not _check_inputs(f, case, scenarios, schedule, a):
        return CheckReport(tuple(f.messages), f.count, nan_cost, math.nan)
    dt = subperiod_hours(k)
    try:
        weight = energy_weight(k, schedule.cost_convention)
    except ValueError as exc:
        f.note(f"(1) {exc}")
        weight = math.nan

    up, down = _check_units(f, case, a, k, dt)
    _check_storage(f, case, a, k, dt)
    _check_loads(f, case, a, k, dt)
    mismatch = _check_balance_and_grid(f, case, a, k, a["p_sch"], penalty)

    if deviation_cost is not None:
        d = (a["dispatch.p_m"] - per_subperiod(np.asarray(p_sch, float), k)[None, :]).reshape(-1, HOURS, k, 1)
        rate = np.max(d * deviation_cost.slope[None, :, None, :] + deviation_cost.intercept[None, :, None, :], axis=-1)
        mismatch, penalty = rate.reshape(len(d), HOURS * k), 1.0  # $/h per sub-period, counted at a rate of 1
    take = schedule.take_award if take_award is None else take_award
    shortfall = None
    if take:
        shortfall = np.maximum(0.0, per_subperiod(a["p_sch"], k)[None, :] * a["scenarios.connected"] - a["dispatch.p_m"])
    cost = _cost(case, a, up, down, mismatch, penalty, weight, import_price, shortfall)
    objective = cost.total
    if not _close(objective, float(schedule.objective)):
        f.note(f"(1) objective: schedule states {schedule.objective:.10g}, recomputed {objective:.10g} "
               f"(off by {schedule.objective - objective:.6g})")
    for term, value in {**cost.as_dict(), "energy": cost.energy}.items():
        stated = getattr(schedule.cost, term)
        if not _close(value, float(stated)):
            f.note(f"(1) cost breakdown {term}: schedule states {stated:.10g}, recomputed {value:.10g}")
    return CheckReport(tuple(f.messages), f.count, cost, objective)
