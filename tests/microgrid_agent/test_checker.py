"""The independent checker passes a hand-built feasible schedule and names each broken constraint by its equation."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from microgrid_agent.checker import MAX_MESSAGES, CheckReport, ScheduleCheckError, check_schedule
from microgrid_agent.schedule import CostBreakdown, Dispatch, FirstStage, StochasticSchedule, Timings, energy_weight
from scenarios.case import parse_case
from scenarios.generation import ScenarioSet

K, S, N = 2, 2, 48
DT = 1.0 / K
P_SCH = 3.0
ISLANDED = slice(30, 36)  # scenario 1, hours 16-18


def _case_data(storage=True, loads=True, renewables=True) -> dict:
    data = {
        "case": {"name": "tiny"},
        "grid": {"p_m_max": 10.0, "p_sch": [P_SCH] * 24, "penalty": 100.0, "voll": 1000.0, "iso_price": [20.0] * 24},
        "fixed_load": {"forecast": [6.0] * 24},
        "uncertainty": {"load": 0.05},
        "units": [
            {"name": "G1", "cost": 20.0, "p_min": 1.0, "p_max": 5.0, "min_up": 3, "min_down": 2, "ramp_up": 2.0,
             "ramp_down": 2.0, "startup_cost": 10.0, "initial_on": True},
            # ramp 1 MW/h x dt = 0.5 < p_min: starting up needs the start-up allowance of (4)
            {"name": "G2", "cost": 40.0, "p_min": 1.0, "p_max": 4.0, "min_up": 2, "min_down": 2, "ramp_up": 1.0,
             "ramp_down": 1.0, "startup_cost": 5.0, "shutdown_cost": 2.0, "initial_on": False},
        ],
    }
    if renewables:
        data["renewables"] = [{"name": "wind", "capacity": 2.0, "forecast": [1.0] * 24}]
    if storage:
        data["storage"] = {"name": "ES", "c_max": 4.0, "p_dch_min": 0.2, "p_dch_max": 1.0, "p_ch_min": 0.2,
                           "p_ch_max": 1.0, "min_charge": 2, "min_discharge": 2, "c_initial": 2.0}
    if loads:
        data["loads"] = [{"name": "L1", "d_min": 0.1, "d_max": 1.0, "energy": 2.0, "alpha": 10, "beta": 14,
                          "min_up": 2}]
    return data


def _hours(*hours: int) -> np.ndarray:
    """A (24,) 0/1 row, 1 at the given 1-based hours."""
    row = np.zeros(24)
    row[[h - 1 for h in hours]] = 1.0
    return row


def _sub(hourly: np.ndarray) -> np.ndarray:
    return np.repeat(hourly, K, axis=-1)


def _scenarios(case) -> ScenarioSet:
    n = np.arange(N)
    load = np.stack([6.0 + 0.05 * np.sin(n), 7.0 + 0.05 * np.cos(n)])
    renewable = np.full((len(case.renewables), S, N), 0.0)
    if case.renewables:
        renewable[0] = [[0.8] * N, [1.2] * N]
    connected = np.ones((S, N))
    connected[1, ISLANDED] = 0.0
    return ScenarioSet(subperiods=K, probability=np.array([0.6, 0.4]), load=load, renewable=renewable,
                       connected=connected)


def _design(case) -> dict:
    """The decisions of a feasible schedule; `_build` derives the rest (balance, soc, mismatch, cost)."""
    commit = np.vstack([np.ones(24), _hours(8, 9, 10, 11, 12)])
    p_unit = np.stack([np.full((S, N), 1.8), np.broadcast_to(_sub(commit[1]), (S, N)) * 1.0])
    charging, discharging = _hours(3, 4), _hours(20, 21)
    p_storage = np.broadcast_to(_sub(discharging) * 0.5 - _sub(charging) * 0.5, (S, N)).copy()
    if case.storage is None:
        charging, discharging, p_storage = np.zeros(24), np.zeros(24), np.zeros((S, N))
    load_on = np.array([_hours(10, 11, 12, 13)] * len(case.loads)).reshape(len(case.loads), 24)
    d_load = np.broadcast_to(_sub(load_on)[:, None, :] * 0.5, (len(case.loads), S, N)).copy()
    return {"commit": commit, "p_unit": p_unit, "charging": charging, "discharging": discharging,
            "p_storage": p_storage, "load_on": load_on, "d_load": d_load}


def _build(case, scen, design, penalty=None, p_sch=None) -> StochasticSchedule:
    """Close the balance with the grid (shedding load when islanded) and state the cost, computed here by hand."""
    penalty = case.grid.penalty if penalty is None else penalty
    p_sch = np.asarray(case.grid.p_sch if p_sch is None else p_sch)
    commit = design["commit"]
    initial = np.array([[u.initial_on] for u in case.units], dtype=float)
    prev = np.hstack([initial, commit[:, :-1]])
    startup, shutdown = np.maximum(0, commit - prev), np.maximum(0, prev - commit)
    p_ren = scen.renewable.copy()
    c0 = case.storage.c_initial if case.storage else 0.0
    soc = c0 - np.cumsum(design["p_storage"], axis=1) * DT
    residual = scen.load + design["d_load"].sum(axis=0) - design["p_unit"].sum(axis=0) - p_ren.sum(axis=0) \
        - design["p_storage"]
    p_m = residual * scen.connected
    shed = residual * (1 - scen.connected)
    assert (shed >= 0).all()
    dp_plus = np.maximum(0.0, p_m - _sub(p_sch))
    pr, ew = scen.probability, energy_weight(K, "real")
    costs = np.array([u.cost for u in case.units])
    generation = sum(pr[s] * ew * (costs[:, None] * design["p_unit"][:, s, :]).sum() for s in range(S))
    start = sum(u.startup_cost * startup[g].sum() + u.shutdown_cost * shutdown[g].sum()
                for g, u in enumerate(case.units))
    curtail = sum(pr[s] * ew * case.grid.voll * shed[s].sum() for s in range(S))
    pen = 0.0 if np.isinf(penalty) else sum(pr[s] * ew * penalty * dp_plus[s].sum() for s in range(S))
    cost = CostBreakdown(generation, start, curtail, pen)
    return StochasticSchedule(
        status="optimal", objective=cost.total, bound=cost.total, cost=cost,
        first=FirstStage(commitment=commit, startup=startup, shutdown=shutdown, discharging=design["discharging"],
                         charging=design["charging"], load_on=design["load_on"]),
        dispatch=Dispatch(p_unit=design["p_unit"], p_renewable=p_ren, p_storage=design["p_storage"], soc=soc,
                          d_load=design["d_load"], p_m=p_m, load_shed=shed, dp_plus=dp_plus),
        probability=scen.probability.copy(), subperiods=K, penalty=penalty, cost_convention="real",
        timings=Timings(0.0, 0.0, 0.0), unit_names=tuple(u.name for u in case.units),
        load_names=tuple(d.name for d in case.loads))


@pytest.fixture(scope="module")
def case():
    return parse_case(_case_data())


@pytest.fixture(scope="module")
def scen(case):
    return _scenarios(case)


@pytest.fixture
def design(case):
    return _design(case)


@pytest.fixture(scope="module")
def good(case, scen):
    return _build(case, scen, _design(case))


def _equations(report: CheckReport) -> set[str]:
    return {m.group(1) for v in report.violations if (m := re.match(r"\((\d+)\)", v))}


def _with_dispatch(schedule, **changes):
    return replace(schedule, dispatch=replace(schedule.dispatch, **changes))


def _with_first(schedule, **changes):
    return replace(schedule, first=replace(schedule.first, **changes))


def test_feasible_schedule_passes(case, scen, good):
    report = check_schedule(case, scen, good)
    assert report.ok, report.summary()
    assert report.violations == () and report.count == 0
    assert report.objective == pytest.approx(good.objective)
    assert report.cost.curtailment > 0 and report.cost.penalty > 0 and report.cost.startup == 7.0
    report.raise_if_failed()


def test_paper_cost_convention_scales_energy_terms(case, scen, good):
    paper = replace(good, cost_convention="paper")
    report = check_schedule(case, scen, paper)
    assert _equations(report) == {"1"}
    assert report.cost.generation == pytest.approx(K * good.cost.generation)
    assert report.cost.startup == pytest.approx(good.cost.startup)


def test_output_above_p_max(case, scen, good):
    p = good.dispatch.p_unit.copy()
    p[0, 1, 20] = 5.3
    report = check_schedule(case, scen, _with_dispatch(good, p_unit=p))
    assert any(v.startswith("(3) output above P_max I: unit G1, scenario 1, hour 11 sub-period 1") for v in
               report.violations)


def test_output_without_commitment(case, scen, good):
    p = good.dispatch.p_unit.copy()
    p[1, 0, 0] = 0.2
    assert "3" in _equations(check_schedule(case, scen, _with_dispatch(good, p_unit=p)))


def test_ramp_within_hour(case, scen, design):
    design["p_unit"][1, :, 15] = 1.6  # G2: hour 8 sub-period 2 jumps 0.6 > 0.5, then falls back
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"4", "5"}
    assert any("(4) ramp-up limit: unit G2, scenario 0, hour 8 sub-period 2: violated by 0.1" in v
               for v in report.violations)


def test_ramp_across_hour_boundary(case, scen, design):
    design["p_unit"][0, :, 24:] = 2.9  # G1 steps up 1.1 MW at the start of hour 13, ramp is 1 MW per sub-period
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"4"}
    assert report.count == S


def test_shut_down_allowance_is_p_min(case, scen, design):
    design["p_unit"][1, :, 21] = 1.5  # G2 ramps 1 -> 1.5 -> 2 within its limits, then stops from 2 MW
    design["p_unit"][1, :, 22:24] = 2.0
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"5"}
    assert report.violations[0] == "(5) ramp-down limit: unit G2, scenario 0, hour 13 sub-period 1: violated by 0.5"


def test_minimum_up_time(case, scen, design):
    design["commit"][1] = _hours(8)
    design["p_unit"][1] = np.broadcast_to(_sub(_hours(8)), (S, N))
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"6"}
    assert report.violations[0].startswith("(6) minimum up time: unit G2, hour 9")


def test_minimum_down_time(case, scen, design):
    design["commit"][1] = _hours(8, 9, 11, 12)
    design["p_unit"][1] = np.broadcast_to(_sub(design["commit"][1]), (S, N))
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"7"}


def test_wrong_startup_indicator(case, scen, good):
    y = good.first.startup.copy()
    y[1, 7] = 0.0
    report = check_schedule(case, scen, _with_first(good, startup=y))
    assert "6" in _equations(report)
    assert any("start-up y != max" in v for v in report.violations)


def test_non_binary_commitment(case, scen, good):
    commit = good.first.commitment.copy()
    commit[0, 5] = 0.7
    report = check_schedule(case, scen, _with_first(good, commitment=commit))
    assert any(v.startswith("(3) commitment I not binary: unit G1, hour 6") for v in report.violations)


def test_balance(case, scen, good):
    load = scen.load.copy()
    load[1, 3] += 0.25
    report = check_schedule(case, replace(scen, load=load), good)
    assert _equations(report) == {"2"}
    assert report.violations == ("(2) power balance: scenario 1, hour 2 sub-period 2: violated by 0.25",)


def test_renewable_above_availability(case, scen, good):
    ren = good.dispatch.p_renewable.copy()
    ren[0, 0, 7] += 0.1
    report = check_schedule(case, scen, _with_dispatch(good, p_renewable=ren))
    assert any(v.startswith("(2) renewable output above availability: renewable wind") for v in report.violations)


def test_soc_continuity(case, scen, good):
    soc = good.dispatch.soc.copy()
    soc[0, 10] += 0.3
    report = check_schedule(case, scen, _with_dispatch(good, soc=soc))
    assert _equations(report) == {"11"}
    assert report.count == 2


def test_storage_end_of_day_and_power(case, scen, design):
    design["p_storage"][:, 40:42] = 0.9  # discharging harder in hour 21: ends below the initial state
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"12"}
    design = _design(case)
    design["p_storage"][:, 5] = 0.0  # idle in a charging hour: (8) needs p <= -P_ch_min
    assert "8" in _equations(check_schedule(case, scen, _build(case, scen, design)))


def test_storage_charge_and_discharge_together(case, scen, good):
    u = good.first.discharging.copy()
    u[2] = 1.0
    report = check_schedule(case, scen, _with_first(good, discharging=u))
    assert "10" in _equations(report)


def test_minimum_charging_binds_charging_state(case, scen, design):
    design["charging"] = _hours(3)  # one hour of charging, MC = 2
    design["p_storage"] = np.broadcast_to(_sub(design["discharging"]) * 0.25 - _sub(_hours(3)) * 0.5, (S, N)).copy()
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"13"}


def test_minimum_discharging_binds_discharging_state(case, scen, design):
    design["discharging"] = _hours(20)
    design["p_storage"] = np.broadcast_to(_sub(_hours(20)) * 0.5 - _sub(design["charging"]) * 0.25, (S, N)).copy()
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"14"}


def test_energy_short(case, scen, design):
    design["d_load"][0, :, 24:26] = 0.4  # hour 13 at 0.4 MW: 1.9 MWh of the 2 required
    report = check_schedule(case, scen, _build(case, scen, design))
    assert _equations(report) == {"16"}
    assert report.violations[0] == "(16) energy in window != E_d: load L1, scenario 0: violated by 0.1"


def test_load_outside_window_and_minimum_operating_time(case, scen, design):
    design["load_on"][0] = _hours(9, 10, 11, 12)
    design["d_load"][0] = np.broadcast_to(_sub(_hours(9, 10, 11, 12, 13)) * 0.4, (S, N))
    report = check_schedule(case, scen, _build(case, scen, design))
    assert {"15", "16"} <= _equations(report)
    design = _design(case)
    design["load_on"][0] = _hours(10, 12, 13, 14)
    design["d_load"][0] = np.broadcast_to(_sub(design["load_on"][0]) * 0.5, (S, N))
    assert _equations(check_schedule(case, scen, _build(case, scen, design))) == {"17"}


def test_islanded_transfer(case, scen, good):
    p_m, shed = good.dispatch.p_m.copy(), good.dispatch.load_shed.copy()
    p_m[1, 31] += 0.5
    shed[1, 31] -= 0.5
    report = check_schedule(case, scen, _with_dispatch(good, p_m=p_m, load_shed=shed))
    assert "18" in _equations(report)
    assert any(v.startswith("(18) grid transfer above P_M_max U: scenario 1, hour 16 sub-period 2") for v in
               report.violations)


def test_wrong_positive_mismatch(case, scen, good):
    dp = good.dispatch.dp_plus.copy()
    dp[0, 3] += 0.2
    report = check_schedule(case, scen, _with_dispatch(good, dp_plus=dp))
    assert _equations(report) == {"19"}


def test_infinite_penalty(case, scen, design):
    high = [9.0] * 24
    ok = _build(case, scen, design, penalty=float("inf"), p_sch=high)
    assert check_schedule(case, scen, ok, p_sch=high).ok
    bad = _build(case, scen, design, penalty=float("inf"))  # P_M above the 3 MW award in places
    report = check_schedule(case, scen, bad)
    assert _equations(report) == {"19"}
    assert any("infinite penalty: grid transfer above P_sch" in v for v in report.violations)
    assert report.cost.penalty == 0.0


def test_penalty_override(case, scen, good):
    report = check_schedule(case, scen, good, penalty=2 * case.grid.penalty)
    assert _equations(report) == {"1"}
    assert report.cost.penalty == pytest.approx(2 * good.cost.penalty)


def test_cost_mismatch(case, scen, good):
    report = check_schedule(case, scen, replace(good, objective=good.objective + 10.0))
    assert _equations(report) == {"1"}
    assert not report.ok and report.count == 1
    assert report.violations[0].startswith("(1) objective: schedule states")
    tiny = check_schedule(case, scen, replace(good, objective=good.objective + 1e-4))
    assert tiny.ok


def test_probabilities(case, scen, good):
    report = check_schedule(case, replace(scen, probability=np.array([0.7, 0.4])), good)
    assert any("sum to" in v for v in report.violations)


def test_nan_reported(case, scen, good):
    p_m = good.dispatch.p_m.copy()
    p_m[0, 0] = np.nan
    report = check_schedule(case, scen, _with_dispatch(good, p_m=p_m))
    assert not report.ok
    assert any("dispatch.p_m has 1 NaN" in v for v in report.violations)


def test_wrong_shape_reported_not_raised(case, scen, good):
    report = check_schedule(case, scen, _with_dispatch(good, p_m=good.dispatch.p_m[:, :-1]))
    assert not report.ok
    assert report.violations == ("shape: dispatch.p_m is (2, 47), expected (2, 48)",)


def test_many_violations_are_capped_but_counted(case, scen, good):
    report = check_schedule(case, scen, _with_dispatch(good, p_unit=good.dispatch.p_unit + 10.0))
    assert len(report.violations) <= MAX_MESSAGES
    assert report.count > 2 * S * N


def test_raise_if_failed(case, scen, good):
    bad = replace(good, objective=good.objective + 10.0)
    with pytest.raises(ScheduleCheckError, match=r"1 violation.*\n  \(1\) objective") as err:
        check_schedule(case, scen, bad).raise_if_failed()
    assert isinstance(err.value, AssertionError)


def test_case_without_storage_loads_or_renewables():
    case = parse_case(_case_data(storage=False, loads=False, renewables=False))
    scen = _scenarios(case)
    schedule = _build(case, scen, _design(case))
    assert check_schedule(case, scen, schedule).ok
    p_st = np.full((S, N), 0.1)
    report = check_schedule(case, scen, _with_dispatch(schedule, p_storage=p_st))
    assert "8" in _equations(report)
