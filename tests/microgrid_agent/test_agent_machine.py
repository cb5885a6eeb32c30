"""The agent's decisions driven by hand (microgrid_agent/agent/machine.py): the DMO's messages of a small day go in,
one by one with the computation a driver would measure, and what the agent sends, waits for, asks and solves comes
out. No process, no Zenoh session, no clock: a whole day of a two-unit microgrid takes well under a second."""

from __future__ import annotations

import pickle

import pytest

from messages import (Award, CallForBids, Clock, DaySummary, GridState, MessageError, SettlementStatement, encode,
                      make_receipt)
from messages.schemas import AgentTotals, HandlingTime, MessageCounts, StatementLine
from microgrid_agent.agent.delivery import RefusedPayload
from microgrid_agent.agent.machine import (AgentConfig, AgentMachine, AgentRefused, AskStatement, AwaitReceipts,
                                           Handled, NoStatement, Send, Solve, Solved)
from scenarios.horizon import HOURS
from tests.microgrid_agent.test_model import tiny_case

TOKEN = "5" * 32  # the run's token, which the DMO's clock gives
DAY, NEXT_DAY = "2026-07-01", "2026-07-02"
CONFIG = AgentConfig(scenarios=1, island_hours=0, gap=0.01, time_limit=None, seed=0, method="auto", workers=1,
                     load_scale=(), renewable_scale=())
COUNTS = MessageCounts(published=27, received=55, rejected={}, handler_errors=0, ignored={}, sent_again=0, asked=0,
                       faults_injected={})


def dmo(cls, market_day: str = DAY, **fields):
    """A message of the DMO's in this run."""
    return cls(sender="dmo", run=TOKEN, market_day=market_day, **fields)


def clock(days: int = 1, day: int = 1, market_day: str = DAY) -> Clock:
    return dmo(Clock, market_day, phase="registration", deadline_s=60.0, day=day, days=days)


def call_for_bids(market_day: str = DAY) -> CallForBids:
    return dmo(CallForBids, market_day, iso_price_per_mwh=(30.0,) * HOURS, price_floor_per_mwh=-100.0,
               price_cap_per_mwh=1000.0, import_limit_mw=3.0, export_limit_mw=3.0, penalty_per_mwh=80.0, subperiods=1,
               deadline_s=60.0)


def award(p_sch_mw: float = 2.0) -> Award:
    return dmo(Award, agent="mg1", p_sch_mw=(p_sch_mw,) * HOURS, clearing_price_per_mwh=(30.0,) * HOURS,
               penalty_per_mwh=80.0, subperiods=1, rules_version=1, rules="paper")


def grid_state(hour: int) -> GridState:
    return dmo(GridState, hour=hour, subperiods=1, connected=(True,))


def statement(market_day: str = DAY) -> SettlementStatement:
    lines = [StatementLine(hour=h, p_sch_mw=2.0, clearing_price_per_mwh=30.0, energy_charge=60.0, import_mwh=2.0,
                           deviation_mwh=0.0, under_import_mwh=0.0, deviation_penalty=0.0, deviation_credit=0.0,
                           total=60.0, missing=False, missing_subperiods=0) for h in range(1, HOURS + 1)]
    return dmo(SettlementStatement, market_day, agent="mg1", penalty_per_mwh=80.0, credit_per_mwh=0.0,
               rules_version=1, lines=lines, energy_charge=60.0 * HOURS, deviation_penalty=0.0, deviation_credit=0.0,
               total=60.0 * HOURS, missing_subperiods=0)


def summary(market_day: str = DAY) -> DaySummary:
    return dmo(DaySummary, market_day, agents=("mg1",), clearing_price_per_mwh=(30.0,) * HOURS,
               totals={"mg1": AgentTotals(energy_charge=60.0 * HOURS, deviation_penalty=0.0, deviation_credit=0.0,
                                          total=60.0 * HOURS)}, rejected_messages=0, incidents=())


def joined(days: int = 1) -> AgentMachine:
    machine = AgentMachine("mg1", tiny_case(), CONFIG, DAY)
    machine.join(clock(days))
    return machine


def decided(machine: AgentMachine, event) -> list:
    """What the machine does about ``event``, a solve it asks for run at once and its result handed in, as the Zenoh
    driver does."""
    actions = machine.handle(event)
    if actions and isinstance(actions[-1], Solve):
        return actions[:-1] + decided(machine, Solved(actions[-1].job.run()))
    return actions


def handled(machine: AgentMachine, msg) -> tuple[list, list]:
    """Hand ``msg`` in as a driver does, then its computation: the actions of each."""
    actions = decided(machine, msg)
    compute = HandlingTime(kind=msg.kind, hour=getattr(msg, "hour", None), wall_s=0.01, cpu_s=0.01, started_at=1,
                           turn_s=0.0)
    return actions, machine.handle(Handled(compute, COUNTS))


def sent(actions: list) -> list[str]:
    """The kind of what each action sends, or the action's name if it sends nothing."""
    return [a.msg.kind if isinstance(a, Send) else type(a).__name__ for a in actions]


def test_a_day_by_hand_bid_schedule_24_reports_its_agent_day_after_their_receipts_then_done():
    machine = joined()
    registration = machine.registration()
    assert (registration.sender, registration.market_day, registration.case, registration.max_import_mw,
            registration.run) == ("mg1", DAY, "tiny", 3.0, "")  # unstamped: the transport stamps it
    assert sent(handled(machine, call_for_bids())[0]) == ["bid"]
    assert handled(machine, call_for_bids()) == ([], [])  # again: the bid sent stands
    actions, _ = handled(machine, award())
    (schedule,) = actions
    assert schedule.msg.kind == "schedule" and schedule.msg.scenarios == 1
    reports = [handled(machine, grid_state(hour)) for hour in range(1, HOURS + 1)]
    assert [[(a.msg.kind, a.msg.hour) for a in report] for report, _ in reports] == [
        [("meter_report", hour)] for hour in range(1, HOURS + 1)]
    assert [after for _, after in reports[:-1]] == [[]] * (HOURS - 1)
    wait, day = reports[-1][1]
    assert wait == AwaitReceipts() and day.msg.kind == "agent_day"
    assert [(c.kind, c.hour) for c in day.msg.compute] == [("call_for_bids", None)] * 2 + [("award", None)] + [
        ("grid_state", hour) for hour in range(1, HOURS + 1)]
    assert day.msg.messages == COUNTS.model_copy(update={"ignored": {"call_for_bids_again": 1}})  # the machine's
    assert day.msg.units.keys() == {"A", "B"}
    assert handled(machine, statement()) == ([], []) and not machine.done
    assert handled(machine, summary()) == ([], []) and machine.done and machine.summary == summary()


def test_a_summary_before_the_statement_asks_for_it_and_the_day_ends_with_it_or_without():
    machine = joined()
    assert machine.handle(summary()) == [AskStatement()] and not machine.done
    assert machine.handle(summary()) == [] and not machine.done  # asked once
    assert machine.handle(statement()) == [] and machine.done
    machine = joined()
    machine.handle(summary())
    assert machine.handle(NoStatement()) == [] and machine.done and machine.statement is None


def test_a_message_of_the_next_day_while_the_day_ends_is_kept_and_handled_as_the_next_day_begins():
    machine = joined(days=2)
    assert machine.handle(summary()) == [AskStatement()]
    assert machine.handle(call_for_bids(NEXT_DAY)) == []  # the DMO went on while the statement was on its way
    assert machine.day == 1 and machine.ignored == {}
    (bid,) = decided(machine, statement())  # the day ends, and the next one bids at once
    assert (bid.msg.kind, bid.msg.market_day, machine.day, machine.market_day) == ("bid", NEXT_DAY, 2, NEXT_DAY)
    assert machine.handle(Handled(HandlingTime(kind="settlement_statement", hour=None, wall_s=0.2, cpu_s=0.2,
                                               started_at=1, turn_s=0.0), COUNTS)) == []
    assert [c.kind for c in machine.compute] == ["settlement_statement"]  # the bid's time counts in its day
    assert machine.handle(call_for_bids(NEXT_DAY)) == [] and machine.ignored == {"call_for_bids_again": 1}


def test_a_repeated_award_changes_nothing_and_is_counted_and_another_award_is_scheduled_again():
    machine = joined()
    assert sent(decided(machine, award())) == ["schedule"]
    assert machine.handle(award().model_copy(update={"seq": 7, "sent_at": 5})) == []  # a copy
    assert machine.ignored == {"award_again": 1}
    assert sent(decided(machine, award(p_sch_mw=1.0))) == ["schedule"]


def test_the_award_asks_for_a_solve_and_the_schedule_goes_only_once_its_result_is_handed_in():
    machine = joined()
    machine.handle(call_for_bids())
    (solve,) = machine.handle(award())
    assert isinstance(solve, Solve) and machine.operator is None  # nothing is scheduled yet
    with pytest.raises(RuntimeError, match="mg1: GridState handed in while a solve is out"):
        machine.handle(grid_state(1))  # the driver hands the result in first
    schedule = pickle.loads(pickle.dumps(solve.job)).run()  # a value a worker process can run
    (sent_schedule,) = machine.handle(Solved(schedule))
    assert sent_schedule.msg.kind == "schedule" and sent_schedule.msg.expected_cost == schedule.objective
    assert sent(machine.handle(grid_state(1))) == ["meter_report"]
    with pytest.raises(RuntimeError, match="mg1: Solved handed in while no solve is out"):
        machine.handle(Solved(schedule))


def test_the_next_days_messages_kept_while_the_day_ends_wait_for_its_schedules_solve():
    machine = joined(days=2)
    assert machine.handle(summary()) == [AskStatement()]
    next_award = award().model_copy(update={"market_day": NEXT_DAY})
    for msg in (call_for_bids(NEXT_DAY), next_award, grid_state(1).model_copy(update={"market_day": NEXT_DAY})):
        assert machine.handle(msg) == []  # the DMO went on while the statement was on its way
    *bid, solve = machine.handle(statement())  # the next day bids and asks for its schedule; the hour waits
    assert sent(bid) == ["bid"] and isinstance(solve, Solve)
    assert sent(machine.handle(Solved(solve.job.run()))) == ["schedule", "meter_report"]


def test_a_refused_registration_ends_the_agent_with_the_dmos_reason_and_another_refusal_does_not():
    machine = joined()

    def refused(msg, code: str) -> RefusedPayload:
        receipt = make_receipt("mg1", encode(msg), MessageError(f"{msg.kind} refused", code), market_day=DAY)
        return RefusedPayload(receipt, msg.kind, msg.seq)

    registration = machine.registration()
    assert machine.handle(refused(registration, "duplicate")) == []  # a copy of one the DMO took
    with pytest.raises(AgentRefused, match=r"mg1: the DMO refused the registration \(late\): registration refused"):
        machine.handle(refused(registration, "late"))
