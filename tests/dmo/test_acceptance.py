"""Which messages the DMO accepts (dmo/market/acceptance.py, dmo/operator/intake.py), and that the replayed DMO
applies the same rules."""

from __future__ import annotations

import itertools

import pytest

from dmo.market import acceptance
from dmo.market.settlement import READING_TOLERANCE_MW, settle
from dmo.operator import intake
from dmo.operator.results import RunResult
from dmo.operator.finished import FinishedDays
from dmo.operator.state import DayState
from messages import Bid, GridState, MeterReport, Registration, decode, encode, sha256
from messages.schemas import AgentDay, MessageCounts
from scenarios.horizon import HOURS
from tests.dmosim.synthetic import typed

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


@pytest.mark.parametrize("excess", [0.0, READING_TOLERANCE_MW / 2, READING_TOLERANCE_MW, 2 * READING_TOLERANCE_MW,
                                    1e-6])
def test_one_tolerance_decides_acceptance_and_settlement_alike(excess):
    """A reading the DMO accepts is one settlement reads, and one it refuses settlement refuses too: another
    party's reading just above a limit can never stop a day at settlement."""
    msg = report(p_m=(1.0, CAP + excess))
    accepted = acceptance.check_meter_report(msg, 3, 2, {}, REG) is None
    try:
        settle({"mg1": (1.0,) * HOURS}, (40.0,) * HOURS, {"mg1": {2: msg.p_m_mw}}, subperiods=2, p_m_max=CAP,
               p_m_min=4.0, penalty=150.0)
        settled = True
    except ValueError:
        settled = False
    assert accepted == settled == (excess <= READING_TOLERANCE_MW)


@pytest.mark.parametrize("p_m, expected", [
    ((1.0, 0.0), None),
    ((1.0, READING_TOLERANCE_MW), None),
    ((1.0, 0.1), "invalid"),
    ((1.0, -0.1), "invalid"),
])
def test_an_islanded_sub_period_must_read_zero(p_m, expected):
    refusal = acceptance.check_meter_report(report(p_m=p_m), 3, 2, {}, REG, connected=(True, False))
    assert (refusal and refusal[0]) == expected
    assert acceptance.check_meter_report(report(p_m=p_m), 3, 2, {}, REG, connected=(True, True)) is None


def test_the_dmo_takes_a_message_of_its_run_and_admitted_process_once_and_refuses_the_others():
    """intake.receive: bound to the run (wrong_run, whatever credentials sent it: a report recorded in an earlier
    run), to the admitted process (stale, unregistered), a copy is the message again, and a restarted process
    rejoins by registering."""
    state = DayState(market_day=DAY, run_token="ab" * 16, phase="realtime", hour=3)
    state.registered["mg1"], state.meter["mg1"] = REG, {}
    state.guard.admit("mg1", 100)
    grid = GridState(sender="dmo", market_day=DAY, hour=3, subperiods=2, connected=(True, True))
    rule = intake.meter_report(state, 3, 2, grid)

    def sent(msg, **stamp):
        msg = msg.model_copy(update={"run": state.run_token, "incarnation": 100, "seq": 5} | stamp)
        payload = encode(msg)
        return intake.receive(state, decode(payload), sha256(payload), rule)

    assert sent(report(), run="cd" * 16).refusal[0] == "wrong_run"  # recorded in another run
    assert sent(report(), incarnation=99).refusal[0] == "stale"      # an earlier process
    assert sent(report(), incarnation=101).refusal[0] == "unregistered"  # a later one, not registered yet
    assert state.meter["mg1"] == {} and state.guard.locked_out() == ["mg1"]
    assert sent(report()).what == intake.ACCEPTED and state.meter["mg1"] == {2: (1.0, 2.0)}
    assert sent(report()).what == intake.AGAIN and state.again == 1  # the same bytes: a receipt, nothing more
    assert sent(report(p_m=(2.0, 2.0))).refusal[0] == "duplicate"     # other content under #5
    assert sent(REG, incarnation=101, seq=0, market_day="2026-07-02").what == intake.REJOINED  # of the run
    assert state.guard.locked_out() == [] and state.rescheduling == {"mg1"}
    assert sent(report(), seq=6).refusal[0] == "stale"  # the old process is gone


def agent_day(market_day: str, total: float = 115.0) -> AgentDay:
    return AgentDay(sender="mg1", market_day=market_day, generation=total - 15.0, startup=10.0, curtailment=0.0,
                    penalty=5.0, total=total, curtailment_mwh=0.0, deviation_mwh=0.1, units={}, stored_mwh=None,
                    compute=(), messages=MessageCounts(published=1, received=1, rejected={}, handler_errors=0,
                                                       ignored={}, sent_again=0, asked=0, faults_injected={}))


def test_a_realised_day_is_taken_once_its_day_is_operated_whatever_the_phase_and_settles_nothing():
    """intake.receive: an agent_day is taken from the day's last real-time hour on, also after the next day began,
    once per agent and day; the phase's rule is never asked (here it refuses everything), and the day's meter
    readings, which settlement reads, stay as they were."""
    state = DayState(market_day=DAY, run_token="ab" * 16, phase="realtime", hour=23, day=2)  # the run began 06-30
    state.registered["mg1"], state.meter["mg1"] = REG, {}
    state.guard.admit("mg1", 100)
    seq = iter(range(10, 100))

    def sent(msg):
        payload = encode(msg.model_copy(update={"run": state.run_token, "incarnation": 100, "seq": next(seq)}))
        return intake.receive(state, decode(payload), sha256(payload), intake.out_of_phase(state))

    assert sent(agent_day(DAY)).refusal == ("invalid",
                                            f"agent_day of {DAY} before its last hour (now realtime hour 23)")
    state.hour = HOURS
    assert sent(agent_day(DAY)).what == intake.ACCEPTED and state.realised["mg1"] == {DAY}
    assert sent(agent_day(DAY, total=215.0)).refusal[0] == "duplicate" and state.realised["mg1"] == {DAY}
    state.start_day(3, "2026-07-02")  # the next day began: the first day's realised day still comes in
    assert sent(agent_day("2026-06-30")).what == intake.ACCEPTED
    assert sent(agent_day("2026-07-02")).refusal[0] == "invalid"  # being bid for, not operated
    for never in ("2026-07-03", "2026-06-29"):  # not a day this run has operated
        assert sent(agent_day(never)).refusal[0] == "wrong_day"
    assert sorted(state.realised["mg1"]) == ["2026-06-30", DAY] and state.meter["mg1"] == {}
    assert state.accepted["agent_day"] == 1  # today's count; the realised days belong to the run


def test_the_dmos_result_gives_each_agents_realised_days_in_order_and_none_for_an_agent_that_sent_none():
    finished = FinishedDays()  # where the DMO keeps them as the run goes
    for day in typed({"days": [{"day": 1, "market_day": "2026-06-30"}, {"day": 2, "market_day": DAY}]}).days:
        finished.day(day)
    finished.realised(agent_day(DAY, 215.0))  # in the order they came, not of their days
    finished.realised(agent_day("2026-06-30"))
    days, taken = finished.read()
    result = RunResult(days, "paper", ["mg1", "mg2"], taken)
    realised = result.realised_days(["mg1", "mg2"])
    assert [(d.day, d.market_day, d.total) for d in realised["mg1"]] == [(1, "2026-06-30", 115.0), (2, DAY, 215.0)]
    assert realised["mg2"] == [] and "sender" not in realised["mg1"][0].model_dump()
    assert realised["mg1"][0].messages.asked == 0


FEEDER_BUSES = ("0", "1", "2", "3", "4")  # feeder5: substation 0


@pytest.mark.parametrize("placed", [None, "2"])
def test_a_rejoin_is_held_to_the_bus_rule_of_a_registration_for_every_bus(placed):
    """Every pair of (first registration's bus, rejoin's bus) over feeder5's buses, none named and one that does not
    exist, with the agent placed by the run or not: a restarted process rejoins exactly when its registration would
    be taken as a first one and puts the agent at the bus it was registered at; otherwise it is refused and the old
    process stays admitted."""
    from scenarios.network import load_network

    network, placement = load_network("feeder5"), {} if placed is None else {"mg1": placed}
    candidates = (None, *FEEDER_BUSES, "99")
    for first_bus, again_bus in itertools.product(candidates, candidates):
        state = DayState(market_day=DAY, run_token="ab" * 16)

        def sent(bus, incarnation, rule):
            msg = REG.model_copy(update={"run": state.run_token, "incarnation": incarnation, "seq": 0, "bus": bus})
            payload = encode(msg)
            return intake.receive(state, decode(payload), sha256(payload), rule, network, placement)

        first = sent(first_bus, 100, intake.registration(state, network, placement))
        at = first_bus if first_bus is not None else placed
        valid = at not in (None, "0", "99") and (placed is None or at == placed)
        assert first.taken == valid, (first_bus, first)
        if not valid:
            continue
        state.phase = "realtime"
        again = sent(again_bus, 101, intake.out_of_phase(state))
        again_at = again_bus if again_bus is not None else placed
        assert (again.what == intake.REJOINED) == (again_at == at), (first_bus, again_bus, again)
        if again_at != at:
            assert again.refusal[0] == "invalid" and "cannot rejoin" in again.refusal[1]
            assert state.guard.incarnation["mg1"] == 100  # the registered process stays the admitted one
