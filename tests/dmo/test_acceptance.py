"""Which messages the DMO accepts (dmo/market/acceptance.py), and that the replayed DMO applies the same rules."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from dmo.market import acceptance
from dmo.replay.as_dmo import AsDmo
from messages import Bid, Keys, MeterReport, Registration, Schedule
from scenarios.horizon import HOURS

DAY = "2026-07-01"
CAP = 10.0
REG = Registration(sender="mg1", market_day=DAY, case="paper", max_import_mw=CAP, max_export_mw=4.0)


def report(hour=3, p_m=(1.0, 2.0), subperiods=None, day=DAY):
    return MeterReport(sender="mg1", market_day=day, hour=hour, subperiods=subperiods or len(p_m), p_m_mw=p_m,
                       deviation_mw=(0.0,) * len(p_m))


@pytest.mark.parametrize("msg, hour, reported, expected", [
    (report(), 3, {}, None),
    (report(p_m=(1.0, 2.0, 3.0)), 3, {}, ("invalid", "3 sub-periods, the day has 2")),
    (report(hour=2), 3, {}, ("late", "meter report for hour 2 during hour 3")),
    (report(hour=4), 3, {}, ("invalid", "meter report for hour 4 during hour 3")),
    (report(), 3, {2: (1.0, 1.0)}, ("duplicate", "second meter report for hour 3")),
    (report(p_m=(1.0, CAP + 0.5)), 3, {}, ("invalid", f"P_M {CAP + 0.5} MW above registered max import {CAP}")),
    (report(p_m=(1.0, CAP + 1e-10)), 3, {}, None),  # float noise, not energy
    (report(p_m=(-4.5, 1.0)), 3, {}, ("invalid", "P_M -4.5 MW below registered max export -4.0")),
    (report(p_m=(-4.0, 1.0)), 3, {}, None),
])
def test_meter_report_acceptance(msg, hour, reported, expected):
    assert acceptance.check_meter_report(msg, hour, 2, reported, REG) == expected


def test_out_of_phase_messages_are_late_once_their_phase_has_passed_else_invalid():
    bid = Bid(sender="mg1", market_day=DAY, hours=((),) * HOURS)
    assert acceptance.out_of_phase(bid, "realtime")[0] == "late"
    assert acceptance.out_of_phase(report(), "scheduling")[0] == "invalid"
    assert acceptance.out_of_phase(report(), "settlement")[0] == "late"
    reg = Registration(sender="mg9", market_day=DAY, case="paper", max_import_mw=CAP, max_export_mw=CAP)
    assert acceptance.out_of_phase(reg, "bidding") == (
        "late", "registration is closed (now bidding): mg9 is not an agent of this day")
    assert acceptance.check_day(report(day="2026-07-02"), DAY)[0] == "wrong_day"
    assert acceptance.check_registered(bid, {})[0] == "unregistered"
    assert acceptance.check_registered(reg, {}) is None
    assert acceptance.repeated("bid", "mg1") == ("duplicate", "second bid from mg1; the first one stands")


def test_the_replayed_dmo_refuses_what_the_live_one_refuses():
    bus = SimpleNamespace(keys=Keys("replay1"), on_reject=None)
    terms = SimpleNamespace(subperiods=2)
    driver = AsDmo(bus, SimpleNamespace(market_day=DAY, terms=terms), "mg1", [], 1.0)
    reg = REG
    assert driver.refusal(report()) == acceptance.check_registered(report(), {})
    driver.registration = reg
    driver.phase, driver.hour = "realtime", 3
    for msg, reported in ((report(), {}), (report(hour=2), {}), (report(p_m=(1.0, 11.0)), {}),
                          (report(p_m=(-5.0, 1.0)), {}), (report(), {2: (0.0, 0.0)}), (report(p_m=(1.0,)), {})):
        driver.meter = dict(reported)
        assert driver.refusal(msg) == acceptance.check_meter_report(msg, 3, 2, reported, REG)
    assert driver.refusal(reg) == acceptance.repeated("registration", "mg1")
    schedule = Schedule(sender="mg1", market_day=DAY, status="optimal", commitment={}, expected_cost=0.0,
                        p_m_expected_mw=(0.0,) * HOURS, scenarios=1)
    assert driver.refusal(schedule) == acceptance.out_of_phase(schedule, "realtime")
    driver.phase, driver.hour = "scheduling", None
    assert driver.refusal(schedule) is None
    driver.answered.add("schedule")
    assert driver.refusal(schedule) == acceptance.repeated("schedule", "mg1")
