"""Real-time operation of a committed microgrid through a realised day, hour by hour (docs/agent.md).

Each hour the operator re-solves the rest of the day as an LP: the day-ahead first stage (commitment, storage
mode, load states) fixed, one scenario whose past and current hour are the realised load, renewables and the
connection the DMO announced, and whose future is the forecast, grid-connected. Sub-periods already operated are
pinned to what was done, so the state of charge, ramps and load energy carry through the day; the current hour's
values are then committed. Each LP extends the previous one's plan, which stays feasible for it (renewable spill
and load curtailment absorb any surprise), so a day that started feasible stays feasible; an islanded hour whose
generation the microgrid cannot take is operated again with an outlet for the surplus (docs/agent.md,
"Feasibility").

On a feeder the DMO's grid state also gives the hour's operating envelope, a room below the award and one above: P_M is
then held within it in the hour's grid-connected sub-periods, unless the hour cannot be operated so, in which case
it is operated without the envelope and its result says so (docs/network.md, "Operating envelopes").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from scenarios.case import Case
from scenarios.days import Midnight, hours_in_state
from scenarios.generation import ScenarioSet, forecast_scenario
from scenarios.horizon import HOURS, per_subperiod

from ..model import DeviationCost, Params
from ..schedule import CostBreakdown, Dispatch, FirstStage, StochasticSchedule, Timings, energy_weight, start_indicators
from ..solvers.extensive import SolveError
from ..solvers.rolling import RollingLP

@dataclass(frozen=True)
class Room:
    """An hour's operating envelope at the microgrid's bus (docs/network.md, "Operating envelopes"): P_M within
    [P^sch - ``export_mw``, P^sch + ``import_mw``] where connected. Both finite and >= 0 (ValueError)."""

    import_mw: float
    export_mw: float

    def __post_init__(self):
        for name in ("import_mw", "export_mw"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"room's {name} must be a finite number of MW >= 0, got {value!r}")


@dataclass(frozen=True)
class HourResult:
    """What one operated hour did, per sub-period (K values): P_M (+ import), its deviation P_M - P^sch, load shed,
    unit outputs (G, K), renewables used (R, K), storage power (+ discharge) and state of charge, adjustable loads
    (D, K), the surplus generation let out while islanded (MW, docs/agent.md, "Feasibility"), and the hour's
    realised cost. ``plan`` is the rolling LP's whole-day solution on ``plan_scenario``.
    ``room``: the operating envelope P_M was held within (``Room``, where connected), None if the
    hour had none; ``envelope_infeasible``: the hour had one but could not be operated within it, and was operated
    without."""

    hour: int
    connected: np.ndarray
    p_m: np.ndarray
    deviation: np.ndarray
    load_shed: np.ndarray
    p_unit: np.ndarray
    p_renewable: np.ndarray
    p_storage: np.ndarray
    soc: np.ndarray
    d_load: np.ndarray
    surplus: np.ndarray
    soc_end: float
    cost: CostBreakdown
    plan: StochasticSchedule
    plan_scenario: ScenarioSet
    room: Room | None = None
    envelope_infeasible: bool = False


@dataclass(frozen=True)
class RealisedDay:
    """The realised day: ``scenario`` holds the realised load and renewables with the announced connection, and
    ``schedule`` the operated dispatch as a one-scenario schedule (its objective the realised cost), so
    ``checker.check_schedule(case, scenario, schedule, p_sch=..., penalty=..., deviation_cost=...)`` verifies it;
    in a sub-period that let ``surplus`` generation out while islanded (MW, per sub-period), the balance (2) is off
    by that much (docs/agent.md, "Feasibility")."""

    scenario: ScenarioSet
    schedule: StochasticSchedule
    p_sch: np.ndarray
    penalty: float
    deviation_cost: DeviationCost | None = None  # the announced rule's, priced instead of the penalty
    surplus: np.ndarray | None = None

    @property
    def cost(self) -> CostBreakdown:
        return self.schedule.cost

    @property
    def p_m(self) -> np.ndarray:
        return self.schedule.dispatch.p_m[0]

    @property
    def deviation(self) -> np.ndarray:
        return self.p_m - per_subperiod(self.p_sch, self.scenario.subperiods)


class Operator:
    """Operates one microgrid through a realised day. ``first_stage`` is ``model.first_stage_of(schedule)``;
    ``realised`` and ``forecast`` are one-scenario sets at ``subperiods`` (``forecast`` defaults to the exact
    expected forecast, grid-connected); ``p_sch`` (24,), ``penalty`` and ``deviation_cost`` (the announced rule's,
    if the model carries it: ``machine.award_params``) are the award's."""

    def __init__(self, case: Case, first_stage: dict, p_sch: Sequence[float], penalty: float, subperiods: int,
                 realised: ScenarioSet, forecast: ScenarioSet | None = None, time_limit: float | None = None,
                 deviation_cost: DeviationCost | None = None):
        self.case, self.K = case, int(subperiods)
        forecast = forecast_scenario(case, self.K) if forecast is None else forecast
        for what, scen in (("realised", realised), ("forecast", forecast)):
            if scen.S != 1 or scen.subperiods != self.K:
                raise ValueError(f"{what} must be one scenario at {self.K} sub-periods per hour, "
                                 f"got {scen.S} at {scen.subperiods}")
        self.p_sch = np.asarray(p_sch, float).reshape(HOURS)
        self.penalty, self.deviation_cost = float(penalty), deviation_cost
        if math.isnan(self.penalty) or self.penalty < 0:
            raise ValueError(f"penalty must be >= 0 (or inf), got {penalty}")
        self.realised, self.forecast, self.time_limit = realised, forecast, time_limit
        G, R, Dn, N = len(case.units), len(case.renewables), len(case.loads), HOURS * self.K
        self.first = self._first_stage(first_stage)
        # What is done is pinned: the second-stage variables that carry the day's state. dP+ is only a cost,
        # recomputed from P_M (and with an infinite penalty the model fixes it to 0, which a pinned positive part
        # where islanded would contradict).
        self._done = {"P": np.zeros((G, N)), "Pr": np.zeros((R, N)), "Pst": np.zeros((1, N)),
                      "C": np.zeros((1, N)), "D": np.zeros((Dn, N)), "PM": np.zeros((1, N)), "LS": np.zeros((1, N)),
                      "S": np.zeros((1, N))}  # and the surplus let out while islanded (solvers/rolling.py)
        self._connected = np.ones(N)
        self._hours: list[HourResult] = []
        self._lp = RollingLP(case, Params(self.p_sch, self.penalty, deviation_cost=self.deviation_cost), self.first,
                             forecast)

    def _first_stage(self, given: dict) -> FirstStage:
        case = self.case
        G, Dn = len(case.units), len(case.loads)
        commitment = np.asarray(given["I"], float).reshape(G, HOURS)
        discharging = np.asarray(given.get("u", np.zeros(HOURS)), float).reshape(HOURS)
        charging = np.asarray(given.get("v", np.zeros(HOURS)), float).reshape(HOURS)
        load_on = np.asarray(given.get("z", np.zeros((Dn, HOURS))), float).reshape(Dn, HOURS)
        initial = case.unit_array("initial_on")
        return FirstStage(commitment, start_indicators(commitment, initial),
                          start_indicators(1.0 - commitment, 1.0 - initial),
                          discharging, charging, load_on)

    @property
    def next_hour(self) -> int:
        """The hour (1..24) ``operate_hour`` expects next; 25 once the day is over."""
        return len(self._hours) + 1

    @property
    def hours(self) -> tuple[HourResult, ...]:
        return tuple(self._hours)

    def _scenario(self, n1: int) -> ScenarioSet:
        """Realised data and connection up to sub-period n1, the forecast grid-connected after it."""
        load, renewable = self.forecast.load.copy(), self.forecast.renewable.copy()
        load[:, :n1] = self.realised.load[:, :n1]
        renewable[:, :, :n1] = self.realised.renewable[:, :, :n1]
        connected = np.ones((1, HOURS * self.K))
        connected[0, :n1] = self._connected[:n1]
        return ScenarioSet(self.K, np.ones(1), load, renewable, connected)

    def operate_hour(self, hour: int, connected: Sequence[bool], room: Room | None = None) -> HourResult:
        """Operate hour ``hour`` (1..24, in order) with the grid connection of its K sub-periods. ``room``: the
        hour's operating envelope at the microgrid's bus, P_M within it (and its own limits) in the
        connected sub-periods; if the hour's LP is infeasible so, it is operated without (``envelope_infeasible``)."""
        if hour != self.next_hour or not 1 <= hour <= HOURS:
            expected = "none: the day is over" if self.next_hour > HOURS else f"hour {self.next_hour}"
            raise ValueError(f"hours must be operated in order 1..{HOURS}: got hour {hour}, expected {expected}")
        if room is not None and not isinstance(room, Room):
            raise ValueError(f"room must be a realtime.Room, got {type(room).__name__}")
        return self._operate(hour, hour, [connected], room)[0]

    def catch_up(self, hour: int, connected: Mapping[int, Sequence[bool]] | None = None) -> tuple[HourResult, ...]:
        """Operate, in one LP, every hour before ``hour`` not operated yet, so that ``hour`` can be operated next.

        For an agent that missed hours (it restarted, or lost the DMO for a while): the microgrid went on
        meanwhile, following its plan as well as it could; these hours are not reported, and the DMO settles
        them by the missing-data rule. ``connected`` gives the connection of any of them that is known (from a
        grid state received but not operated); the others are taken as grid-connected, as the forecast is.
        Hours already operated stay as they were; an ``hour`` at or before ``next_hour`` does nothing."""
        if not 1 <= hour <= HOURS + 1:
            raise ValueError(f"hour must be 1..{HOURS + 1}, got {hour}")
        first, last = self.next_hour, hour - 1
        if last < first:
            return ()
        known = connected or {}
        return self._operate(first, last, [known.get(h, [True] * self.K) for h in range(first, last + 1)])

    def _operate(self, first: int, last: int, connected: list[Sequence[bool]],
                 room: Room | None = None) -> list[HourResult]:
        """Hours first..last (each with its K connection values) in one rolling LP; past sub-periods pinned; P_M
        within ``room`` of the award (one hour only), unless the LP is infeasible so."""
        n0, n1 = (first - 1) * self.K, last * self.K
        conns = [np.asarray(c) for c in connected]
        for conn, c in zip(conns, connected):
            if conn.shape != (self.K,) or not np.all((conn == 0) | (conn == 1)):
                raise ValueError(f"connected must be {self.K} booleans (one per sub-period), got {c!r}")
        self._connected[n0:n1] = np.concatenate(conns).astype(float)
        scen = self._scenario(n1)
        wanted = None if room is None else self._envelope(n0, n1, room)
        attempts = [(wanted, None)]
        if wanted is not None:
            attempts.append((None, None))  # a day never fails for an envelope
        if not self._connected[n0:n1].all():
            attempts.append((None, (n0, n1)))  # nor for surplus generation while islanded
        for bounds, outlet in attempts:
            try:
                plan, surplus = self._lp.solve(scen, pinned=(n0, self._done), pm_bounds=bounds,
                                               time_limit=self.time_limit, outlet=outlet)
                break
            except SolveError as err:
                failed = err
        else:
            raise SolveError(f"{_hours(first, last, self._connected[n0:n1])} cannot be operated: {failed} "
                             '(docs/agent.md, "Feasibility")')
        infeasible = wanted is not None and bounds is None
        self._commit(plan.dispatch, surplus, n0, n1, bounds)
        kept = None if infeasible else room
        results = [self._hour_result(h, (h - 1) * self.K, h * self.K, plan, scen, kept, infeasible)
                   for h in range(first, last + 1)]
        self._hours.extend(results)
        return results

    def _envelope(self, n0: int, n1: int, room: Room) -> tuple[int, np.ndarray, np.ndarray] | None:
        """P_M's bounds in the sub-periods n0..n1 of one hour: within ``room`` of the award and the registered
        limits where connected, 0 where islanded; None where that is no tighter than the limits (nothing to add)."""
        limit = self.case.grid.p_m_max * self._connected[n0:n1]
        award = per_subperiod(self.p_sch, self.K)[n0:n1]
        connected = self._connected[n0:n1] > 0.5
        lower = np.where(connected, np.maximum(award - room.export_mw, -limit), -limit)
        upper = np.where(connected, np.minimum(award + room.import_mw, limit), limit)
        if (lower <= -limit).all() and (upper >= limit).all():
            return None
        return n0, lower, upper

    def _commit(self, d: Dispatch, surplus: np.ndarray, n0: int, n1: int,
                bounds: tuple[int, np.ndarray, np.ndarray] | None) -> None:
        """Copy the current hour out of the plan and its surplus, clipped to the bounds the next LP pins it within
        (and to the envelope's, ``bounds``, if the LP held P_M within it)."""
        st = self.case.storage
        now = slice(n0, n1)
        self._done["P"][:, now] = d.p_unit[:, 0, now]
        self._done["Pr"][:, now] = np.clip(d.p_renewable[:, 0, now], 0.0, self.realised.renewable[:, 0, now])
        self._done["Pst"][:, now] = d.p_storage[:, now]
        self._done["C"][:, now] = np.clip(d.soc[:, now], 0.0, st.c_max if st is not None else 0.0)
        self._done["D"][:, now] = d.d_load[:, 0, now]
        limit = self.case.grid.p_m_max * self._connected[now]
        lower, upper = (-limit, limit) if bounds is None else bounds[1:]  # the envelope's lie within the limits
        self._done["PM"][:, now] = np.clip(d.p_m[:, now], lower, upper)
        self._done["LS"][:, now] = np.maximum(d.load_shed[:, now], 0.0)
        self._done["S"][0, now] = surplus[now]

    def _cost(self, n0: int, n1: int, hours: slice) -> CostBreakdown:
        """Realised cost of sub-periods n0..n1 and of the commitment transitions in ``hours``."""
        dt = energy_weight(self.K, "real")
        case, now = self.case, slice(n0, n1)
        deviation = self._done["PM"][0] - per_subperiod(self.p_sch, self.K)
        if self.deviation_cost is not None:  # the announced rule's charge ($/h) for each sub-period's deviation
            penalty = dt * math.fsum(self.deviation_cost.rate(deviation)[now])
        else:
            penalty = 0.0 if math.isinf(self.penalty) else self.penalty * dt * math.fsum(np.maximum(deviation[now], 0))
        startup = math.fsum(case.unit_array("startup_cost") @ self.first.startup[:, hours]) + math.fsum(
            case.unit_array("shutdown_cost") @ self.first.shutdown[:, hours])
        return CostBreakdown(
            generation=dt * math.fsum(case.unit_array("cost") @ self._done["P"][:, now]),
            startup=startup,
            curtailment=dt * case.grid.voll * math.fsum(self._done["LS"][0, now]),
            penalty=penalty,
        )

    def _hour_result(self, hour: int, n0: int, n1: int, plan: StochasticSchedule, scen: ScenarioSet,
                     room: Room | None, envelope_infeasible: bool) -> HourResult:
        now, done = slice(n0, n1), self._done
        p_m = done["PM"][0, now].copy()
        return HourResult(
            hour=hour,
            connected=self._connected[now] > 0.5,
            p_m=p_m,
            deviation=p_m - self.p_sch[hour - 1],
            load_shed=done["LS"][0, now].copy(),
            p_unit=done["P"][:, now].copy(),
            p_renewable=done["Pr"][:, now].copy(),
            p_storage=done["Pst"][0, now].copy(),
            soc=done["C"][0, now].copy(),
            d_load=done["D"][:, now].copy(),
            surplus=done["S"][0, now].copy(),
            soc_end=float(done["C"][0, n1 - 1]),
            cost=self._cost(n0, n1, slice(hour - 1, hour)),
            plan=plan,
            plan_scenario=scen,
            room=room,
            envelope_infeasible=envelope_infeasible,
        )

    def midnight(self) -> Midnight:
        """What the microgrid carries into the next day, as its operation ended this one (all 24 hours done): each
        unit's state, output in the last sub-period and hours in that state, and the stored energy."""
        if self.next_hour <= HOURS:
            raise ValueError(f"the day is not over: hours 1..{self.next_hour - 1} of {HOURS} operated")
        on = self.first.commitment[:, -1] > 0.5
        return Midnight(unit_on=tuple(bool(x) for x in on),
                        unit_output_mw=tuple(float(x) for x in self._done["P"][:, -1]),
                        unit_hours=hours_in_state(self.first.commitment),
                        stored_mwh=float(self._done["C"][0, -1]) if self.case.storage is not None else None)

    def day_result(self) -> RealisedDay:
        """The whole operated day as a one-scenario schedule with its realised cost; all 24 hours must be done."""
        if self.next_hour <= HOURS:
            raise ValueError(f"the day is not over: hours 1..{self.next_hour - 1} of {HOURS} operated")
        done, N = self._done, HOURS * self.K
        cost = self._cost(0, N, slice(0, HOURS))
        scen = ScenarioSet(self.K, np.ones(1), self.realised.load.copy(), self.realised.renewable.copy(),
                           self._connected[None, :].copy())
        dispatch = Dispatch(
            p_unit=done["P"][:, None, :].copy(), p_renewable=done["Pr"][:, None, :].copy(),
            p_storage=done["Pst"].copy(), soc=done["C"].copy(), d_load=done["D"][:, None, :].copy(),
            p_m=done["PM"].copy(), load_shed=done["LS"].copy(),
            dp_plus=np.maximum(done["PM"] - per_subperiod(self.p_sch, self.K)[None, :], 0.0),
        )
        timings = [h.plan.timings for h in self._hours]
        schedule = StochasticSchedule(
            status="realised", objective=cost.total, bound=cost.total, cost=cost, first=self.first,
            dispatch=dispatch, probability=np.ones(1), subperiods=self.K, penalty=self.penalty,
            cost_convention="real",
            timings=Timings(*(math.fsum(getattr(t, f) for t in timings) for f in ("build_s", "solve_s", "total_s"))),
            unit_names=tuple(u.name for u in self.case.units), load_names=tuple(d.name for d in self.case.loads),
        )
        return RealisedDay(scen, schedule, self.p_sch.copy(), self.penalty, self.deviation_cost, done["S"][0].copy())


def _hours(first: int, last: int, connected: np.ndarray) -> str:
    """``hour 20 (islanded)``, ``hours 3-5``: the hours of one LP, and how they were connected."""
    hours = f"hour {first}" if first == last else f"hours {first}-{last}"
    if not connected.any():
        return f"{hours} (islanded)"
    return hours if connected.all() else f"{hours} (partly islanded)"
