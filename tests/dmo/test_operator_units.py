"""The DMO's units, each on its own and without a network: the replay guard, the incident log, the journal and
resuming from it, rejoining agents, and the messages the DMO builds."""

from __future__ import annotations

import json

import pytest

from dmo.market.clearing import fixed_awards
from dmo.market.choice import choose
from dmo.market.settlement import RULES, RULES_VERSION, settle
from dmo.operator import incidents, outbox
from dmo.operator.config import DayConfig, draw_islanding
from dmo.operator.guard import REMEMBERED, SequenceGuard
from dmo.operator.history import DayHistory, asks_history
from dmo.operator.incidents import IncidentLog
from dmo.operator.journal import (Journal, accepted_entry, clock_entry, incident_entry, rejected_entry, restore,
                                  run_token_entry, traffic)
from dmo.operator.rejoin import AWARD, CALL_FOR_BIDS, GRID_STATE, readmit, rejoin_refusal, resend_plan
from dmo.operator.state import DayState
from messages import Bid, MeterReport, Registration, decode, encode, sha256
from scenarios.horizon import HOURS

DAY = "2026-07-01"
K = 2


def registration(agent="mg1", case="paper", cap=10.0, seq=0, incarnation=1):
    return Registration(sender=agent, market_day=DAY, case=case, max_import_mw=cap, max_export_mw=cap, seq=seq,
                        incarnation=incarnation)


def meter(agent="mg1", hour=1, p_m=(1.0, 2.0), seq=0, incarnation=1):
    return MeterReport(sender=agent, market_day=DAY, hour=hour, subperiods=len(p_m), p_m_mw=p_m,
                       deviation_mw=tuple(p - 1.0 for p in p_m), seq=seq, incarnation=incarnation)


def config(**kw):
    settings = dict(market_day=DAY, agents=2, iso_price=(40.0,) * HOURS, import_limit=16.0, export_limit=10.0,
                    penalty=150.0, credit=0.0, subperiods=K, islanded_hours=(5, 6), registration_s=60.0, bids_s=60.0,
                    schedule_s=60.0, hour_s=60.0)
    return DayConfig(**(settings | kw))


# --- replay guard ------------------------------------------------------------------------------------------------

def test_guard_takes_copies_as_the_message_again_and_refuses_replays_overtaken_and_earlier_processes():
    guard = SequenceGuard()
    assert guard.check("mg1", 1, 0, registration=True) is None
    guard.admit("mg1", 1)
    for seq in (0, 1, 3):
        assert guard.check("mg1", 1, seq, registration=False) is None
        guard.accept("mg1", seq, sha256(b"%d" % seq))
    assert guard.again("mg1", 1, 1, sha256(b"1")) and not guard.again("mg1", 1, 1, sha256(b"other"))  # a copy, or not
    assert not guard.again("mg1", 2, 1, sha256(b"1"))  # the same bytes are never another process's
    assert guard.check("mg1", 1, 1, registration=False)[0] == "duplicate"  # other content under #1: a replay
    assert guard.check("mg1", 1, 2, registration=False) is None  # overtaken by #3 and never accepted: new
    guard.accept("mg1", 3 + REMEMBERED, sha256(b"far"))
    assert guard.check("mg1", 1, 3, registration=False)[0] == "late"  # too far back to tell whether it was taken
    assert guard.check("mg1", 1, 4, registration=False) is None and guard.check("mg2", 5, 0, False) is None  # new
    assert guard.locked_out() == []
    # a restarted process (a later incarnation) must register before anything else; an earlier one is stale
    guard.heard("mg1", 2)
    assert guard.check("mg1", 2, 0, registration=False)[0] == "unregistered"
    assert guard.check("mg1", 2, 0, registration=True) is None
    assert guard.locked_out() == ["mg1"]  # heard, not admitted
    guard.admit("mg1", 2)  # numbers from 0 again
    assert guard.locked_out() == [] and guard.check("mg1", 2, 0, registration=False) is None
    assert guard.check("mg1", 1, 4, registration=False)[0] == "stale"
    assert not guard.again("mg1", 1, 1, sha256(b"1"))  # what the old process sent is not taken again either
    guard.heard("mg9", 7)  # a stranger that spoke and was never admitted is not of the market
    assert guard.locked_out() == []


def test_the_guard_remembers_a_bounded_window_of_accepted_messages(monkeypatch):
    monkeypatch.setattr("dmo.operator.guard.REMEMBERED", 4)
    guard = SequenceGuard()
    guard.admit("mg1", 1)
    for seq in range(10):
        guard.accept("mg1", seq, sha256(b"%d" % seq))
    assert guard.again("mg1", 1, 9, sha256(b"9")) and guard.again("mg1", 1, 6, sha256(b"6"))
    assert not guard.again("mg1", 1, 5, sha256(b"5")) and guard.check("mg1", 1, 5, registration=False)[0] == "late"
    assert len(guard.accepted["mg1"]) == 4
    storage = guard.accepted["mg1"]
    guard.accept("mg1", 10, sha256(b"10"))  # in the storage allocated when the process was admitted
    assert guard.accepted["mg1"] is storage and len(storage) == 4 and guard.again("mg1", 1, 10, sha256(b"10"))


# --- incidents ---------------------------------------------------------------------------------------------------

def test_rejections_are_listed_up_to_a_cap_then_counted_and_the_list_is_capped(monkeypatch):
    monkeypatch.setattr(incidents, "MAX_LISTED_REJECTIONS", 3)
    monkeypatch.setattr(incidents, "MAX_INCIDENTS", 6)
    log = IncidentLog()
    listed = [log.count_rejection(code) for code in ("late", "late", "invalid", "late", "duplicate")]
    assert listed == [True, True, True, False, False]
    for n in range(7):
        log.add("mg1", "realtime", n + 1, f"incident {n}" + "x" * 600)
    assert all(len(i.reason) == incidents.MAX_REASON for i in log.incidents)
    added = log.close("settlement", None)
    assert [i.reason.split(" ", 2)[:2] for i in added] == [["5", "messages"], ["3", "more"]]
    assert "duplicate 1, invalid 1, late 3" in added[0].reason
    assert len(log.incidents) == 6 and log.incidents[-1] is added[-1]
    assert log.rejected == 5 and log.rejected_by_code == {"late": 3, "invalid": 1, "duplicate": 1}


# --- journal and resume ------------------------------------------------------------------------------------------

def test_a_journal_restores_what_was_accepted_and_where_the_day_stood(tmp_path):
    path = tmp_path / "dmo.journal"
    journal = Journal(path, "run1", DAY)
    journal.write(run_token_entry("ab" * 16))
    journal.write(clock_entry("registration", None))
    for msg in (registration("mg1"), registration("mg2", seq=0)):
        journal.write(accepted_entry(f"dmosim/run1/agent/{msg.sender}/register", encode(msg)))
    journal.write(clock_entry("bidding", None))
    bid = Bid(sender="mg1", market_day=DAY, hours=((),) * HOURS, seq=1, incarnation=1)
    as_received = encode(bid).replace(b'"hours":', b'"hours" :')  # the bytes as they came, not re-encoded
    journal.write(accepted_entry("dmosim/run1/agent/mg1/bid", as_received))
    journal.write(clock_entry("realtime", 3))
    journal.write(accepted_entry("dmosim/run1/agent/mg2/meter",
                                 encode(meter("mg2", hour=3, seq=1 + REMEMBERED))))
    journal.write(incident_entry(IncidentLog().add("mg1", "realtime", 3,
                                                   "late: no meter report for hour 3 by the deadline")))
    journal.write(rejected_entry("duplicate"))
    journal.close()
    with open(path, "a") as f:
        f.write('{"accepted": "cut by a kil')  # a line cut by SIGKILL: the ones before it stand

    again = Journal(path, "run1", DAY)
    state = DayState()
    assert restore(state, again.entries) == (("realtime", 3), [])
    again.close()
    assert (state.phase, state.hour) == ("realtime", 3) and state.run_token == "ab" * 16
    assert sorted(state.registered) == ["mg1", "mg2"] and state.bids["mg1"] == bid
    assert state.meter == {"mg1": {}, "mg2": {2: (1.0, 2.0)}}
    assert state.accepted == {"registration": 2, "bid": 1, "meter_report": 1}
    assert state.guard.again("mg1", 1, 1, sha256(as_received))  # the bid sent again is known for what it is
    assert state.guard.check("mg1", 1, 1, False)[0] == "duplicate" and state.guard.check("mg2", 1, 1, False)[0] == "late"
    assert [i.reason[:4] for i in state.incidents] == ["late"] and state.rejected_by_code == {"duplicate": 1}


def test_a_journal_of_several_days_restores_the_finished_days_and_the_one_under_way(tmp_path):
    journal = Journal(tmp_path / "dmo.journal", "run1", DAY)
    journal.write(clock_entry("registration", None))
    journal.write(accepted_entry("dmosim/run1/agent/mg1/register", encode(registration("mg1"))))
    journal.write(clock_entry("realtime", 24, day=1, market_day=DAY))
    journal.write(accepted_entry("dmosim/run1/agent/mg1/meter", encode(meter("mg1", hour=24, seq=1))))
    journal.write(incident_entry(IncidentLog().add("mg1", "realtime", 24, "late: day one")))
    journal.write(clock_entry("bidding", None, day=2, market_day="2026-07-02"))
    journal.write(accepted_entry("dmosim/run1/agent/mg1/meter", encode(meter("mg1", hour=1, seq=2))))
    journal.close()
    state = DayState()
    clock, finished = restore(state, Journal(tmp_path / "dmo.journal", "run1", DAY).entries)
    assert clock == ("bidding", None) and (state.day, state.market_day) == (2, "2026-07-02")
    (first,) = finished
    assert (first.day, first.market_day) == (1, DAY) and set(first.meter["mg1"]) == {23}
    assert [i.reason for i in first.incidents] == ["late: day one"] and state.incidents == []
    assert set(state.meter["mg1"]) == {0} and sorted(state.registered) == ["mg1"]  # registration carried over
    assert state.guard.check("mg1", 1, 1, False)[0] == "duplicate"  # and so did the replay guard


def test_a_journal_of_another_run_or_day_is_started_afresh(tmp_path):
    path = tmp_path / "dmo.journal"
    journal = Journal(path, "run1", DAY)
    journal.write(clock_entry("bidding", None))
    journal.close()
    for run_id, day in (("run2", DAY), ("run1", "2026-07-02")):
        other = Journal(path, run_id, day)
        other.close()
        assert other.entries == []
        assert [json.loads(line) for line in path.read_text().splitlines()] == [
            {"journal": 1, "run_id": run_id, "market_day": day}]


def test_restoring_a_rejoined_agent_numbers_its_messages_from_zero():
    state = DayState()
    entries = [{"accepted": "k", "message": encode(m).decode()}
               for m in (registration(seq=0), meter(hour=1, seq=5), registration(seq=0, incarnation=2),
                         meter(hour=2, seq=1, incarnation=2))]
    assert restore(state, entries) == (None, [])  # no clock: the day had not started
    assert state.guard.incarnation["mg1"] == 2 and state.guard.check("mg1", 1, 5, False)[0] == "stale"
    assert state.guard.check("mg1", 2, 1, False)[0] == "duplicate" and state.guard.check("mg1", 2, 2, False) is None
    assert set(state.meter["mg1"]) == {0, 1}


def test_the_history_answers_the_latest_of_the_dmo_or_the_whole_traffic_and_survives_a_restart(tmp_path):
    p = "dmosim/run1"
    entries = [(f"{p}/dmo/clock", b'{"phase":"registration"}', 1), (f"{p}/agent/mg1/register", b"reg", 2),
               (f"{p}/dmo/clock", b'{"phase":"bidding"}', 3), (f"{p}/agent/mg1/bid", b"\xff not json", 4),
               (f"{p}/dmo/award/mg1", b"award1", 5), (f"{p}/dmo/award/mg2", b"award2", 6)]
    journal = Journal(tmp_path / "dmo.journal", "run1", DAY)
    histories = {"journaled": DayHistory(journal), "in a scratch file": DayHistory()}
    for entry in entries:
        for history in histories.values():
            history.record(*entry)
    journal.close()
    again = Journal(tmp_path / "dmo.journal", "run1", DAY)
    histories["restarted on the journal"] = DayHistory(again)
    for how, history in histories.items():
        assert history.answer(f"{p}/dmo/clock", "") == [entries[2]], how  # the latest clock
        assert history.answer(f"{p}/**", "") == [entries[2], entries[4], entries[5]], how  # the DMO's, in time order
        assert list(history.answer(f"{p}/**", "history")) == entries, how  # everything, payloads as they came
        with pytest.raises(ValueError, match="history is answered for the whole run only"):
            history.answer(f"{p}/agent/*/bid", "history;since=0")  # an agent may ask only for what it hears
        assert asks_history(f"{p}/**", "history;since=0") and not asks_history(f"{p}/dmo/clock", "history")
        assert list(history.answer(f"{p}/**", "history;since=4")) == entries[3:], how  # what it saw from then on
        with pytest.raises(ValueError, match="since='-1': not a time in whole nanoseconds"):
            history.answer(f"{p}/**", "history;since=-1")
        assert history.answer(f"{p}/dmo/award/mg1", "") == [entries[4]], how
        assert history.answer(f"{p}/dmo/award/*", "") == [entries[4], entries[5]], how
        assert history.answer(f"{p}/dmo/award/mg3", "") == [], how  # a key the DMO never published on
    again.close()
    assert list(traffic(again.entries)) == entries


def test_the_history_since_a_time_reads_the_file_from_a_mark_shortly_before_it(tmp_path, monkeypatch):
    """What the DMO answers for ``since`` is everything at or after it, in the order seen, though times from Zenoh's
    threads come slightly out of order; it reads the file only from the last mark with everything before it older,
    so a day's question does not read the run's days before it."""
    monkeypatch.setattr("dmo.operator.history.MARK_EVERY", 3)
    p = "dmosim/run1"
    times = [1, 2, 4, 3, 5, 6, 8, 7, 9, 10, 12, 11, 13, 14, 15]  # two threads' clocks, interleaved
    entries = [(f"{p}/agent/mg1/meter", b"%d" % i, at) for i, at in enumerate(times)]
    journal = Journal(tmp_path / "dmo.journal", "run1", DAY)
    for history in (DayHistory(journal), DayHistory()):
        for entry in entries:
            history.record(*entry)
        for since in range(0, 17):
            assert list(history.answer(f"{p}/**", f"history;since={since}")) == [e for e in entries if e[2] >= since]
        read = list(history._lines_since(12))  # noqa: SLF001
        assert len(read) == 6  # lines 9-14: everything before line 9 is older than 12, not all before line 12
    journal.close()


def test_a_journal_cut_by_a_kill_goes_on_after_its_last_whole_line(tmp_path):
    path = tmp_path / "dmo.journal"
    journal = Journal(path, "run1", DAY)
    journal.write(clock_entry("bidding", None))
    journal.close()
    with open(path, "ab") as f:
        f.write(b'{"clock":"clearing","ho')  # the kill came mid-line
    again = Journal(path, "run1", DAY)
    assert [e["clock"] for e in again.entries] == ["bidding"] and again.size == path.stat().st_size
    again.write(clock_entry("scheduling", None))
    again.close()
    assert [e["clock"] for e in Journal(path, "run1", DAY).entries] == ["bidding", "scheduling"]


# --- agents that come back ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("phase", ["registration", "bidding", "scheduling", "realtime", "settlement"])
def test_a_restarted_agent_with_the_same_case_and_limits_rejoins_whatever_the_dmo_saw_of_its_presence(phase):
    state = DayState(registered={"mg1": registration()}, phase=phase, hour=4 if phase == "realtime" else None)
    state.count_accepted(registration(), sha256(b"0"))
    state.guard.accept("mg1", 7, sha256(b"7"))
    assert rejoin_refusal(state, registration(seq=3))[0] == "duplicate"  # the same process registering again
    assert rejoin_refusal(state, registration(case="other", incarnation=2))[0] == "invalid"
    assert rejoin_refusal(state, registration(cap=11.0, incarnation=2))[0] == "invalid"
    assert rejoin_refusal(state, registration(incarnation=2)) is None  # not seen to vanish: taken all the same
    readmit(state, registration(incarnation=2))
    assert state.live() == ["mg1"] and state.guard.incarnation["mg1"] == 2
    assert state.rescheduling == ({"mg1"} if phase in ("scheduling", "realtime") else set())
    assert state.guard.check("mg1", 2, 0, False) is None and state.guard.check("mg1", 1, 8, False)[0] == "stale"


@pytest.mark.parametrize("phase, hour, has_bid, cleared, grid, sent", [
    ("registration", None, False, False, False, ()),
    ("bidding", None, False, False, False, (CALL_FOR_BIDS,)),
    ("bidding", None, True, False, False, ()),
    ("scheduling", None, True, True, False, (AWARD,)),
    ("realtime", 5, True, True, True, (AWARD, GRID_STATE)),
    ("realtime", 4, True, True, True, (AWARD,)),  # hour 4 is reported already: it goes on at hour 5
    ("settlement", None, True, True, True, ()),
])
def test_an_agent_that_comes_back_is_sent_what_it_needs_to_go_on(phase, hour, has_bid, cleared, grid, sent):
    state = DayState(phase=phase, hour=hour, meter={"mg1": {3: (1.0,)}})
    if has_bid:
        state.bids["mg1"] = Bid(sender="mg1", market_day=DAY, hours=((),) * HOURS)
    kinds, said = resend_plan(state, "mg1", cleared, grid)
    assert kinds == sent
    assert ("hour 5" in said) == (GRID_STATE in sent) and said.startswith("nothing") == (not sent)


# --- what the DMO publishes --------------------------------------------------------------------------------------

def test_the_dmos_messages_carry_its_terms_and_survive_the_wire():
    c = config(credit=5.0)
    clearing = fixed_awards({"mg1": (1.0,) * HOURS, "mg2": (2.0,) * HOURS}, c.iso_price)
    award = outbox.award(c, 1, clearing, "mg2")
    assert award.p_sch_mw == (2.0,) * HOURS and award.clearing_price_per_mwh == c.iso_price
    assert (award.penalty_per_mwh, award.credit_per_mwh, award.subperiods) == (150.0, 5.0, K)
    assert (award.rules_version, award.rules) == (RULES_VERSION, RULES)
    assert award.congestion == clearing.congested == ("none",) * HOURS  # the clearing's own, on every award
    assert [outbox.grid_state(c, 1, h).connected for h in (4, 5, 6, 7)] == [(True,) * K, (False,) * K,
                                                                        (False,) * K, (True,) * K]
    call = outbox.call_for_bids(c, 1, 12.5)
    assert call.deadline_s == 12.5 and call.import_limit_mw == 16.0 and call.iso_price_per_mwh == c.iso_price
    meters = {"mg1": {h: (1.5, 0.5) for h in range(HOURS)}, "mg2": {}}
    statements, _ = settle(clearing.awards, clearing.price, meters, subperiods=K, penalty=150.0, credit=5.0,
                           p_m_max=10.0)
    message = outbox.statement_message(statements["mg1"], DAY, 150.0, 5.0)
    assert [line.hour for line in message.lines] == list(range(1, HOURS + 1))
    assert message.total == float(statements["mg1"].total) and message.deviation_penalty == 24 * 150.0 * 0.25
    summary = outbox.day_summary(DAY, ["mg2", "mg1"], clearing.price, statements, 3, ())
    assert summary.agents == ("mg1", "mg2") and summary.rejected_messages == 3
    assert summary.totals["mg2"].total == float(statements["mg2"].total)
    for msg in (award, call, message, summary, outbox.clock(c, 1, "realtime", 3, 60.0)):
        assert decode(encode(msg)) == msg


def test_the_award_announces_the_rule_and_its_rates():
    clearing = fixed_awards({"mg1": (1.0,) * HOURS}, config().iso_price)
    paper = outbox.award(config(settlement=choose("paper:penalty=50")), 1, clearing, "mg1")
    assert (paper.penalty_per_mwh, paper.credit_per_mwh) == (50.0, 0.0)  # the rule's own rates
    assert paper.settlement_rule == "paper:penalty=50,credit=0" and paper.rules == RULES
    assert paper.deviation_cost == (((0.0, 0.0), (50.0, 0.0)),) * HOURS
    band = outbox.award(config(settlement=choose("deadband:band_mw=0.5")), 1, clearing, "mg1")
    assert band.penalty_per_mwh == 150.0 and band.rules.startswith(band.settlement_rule + ": f(d) = rate x")
    assert band.deviation_cost[0] == ((0.0, 0.0), (0.0, 0.0), (150.0, -75.0))
    own = outbox.award(config(settlement=choose("examples/settlement_rule.py:capped_penalty:cap=9")), 1, clearing,
                       "mg1")
    assert own.deviation_cost is None and own.rules.startswith(
        "examples/settlement_rule.py:capped_penalty:penalty=150,credit=0,cap=9: The")
    for msg in (paper, band, own):
        assert decode(encode(msg)) == msg


def test_each_day_of_a_run_has_its_own_market_day_and_islanding():
    c = config(days=3, islanding_by_day=((5,), (), (20, 21)))
    assert [c.market_day_of(d) for d in (1, 2, 3)] == [DAY, "2026-07-02", "2026-07-03"]
    clearing = fixed_awards({"mg1": (1.0,) * HOURS}, c.iso_price)
    assert outbox.award(c, 3, clearing, "mg1").market_day == "2026-07-03"
    tick = outbox.clock(c, 2, "bidding", None, 5.0)
    assert (tick.day, tick.days, tick.market_day) == (2, 3, "2026-07-02")
    islanded = {d: [h for h in range(1, HOURS + 1) if not outbox.grid_state(c, d, h).connected[0]] for d in (1, 2, 3)}
    assert islanded == {1: [5], 2: [], 3: [20, 21]}
    with pytest.raises(ValueError, match="gives 2 days"):
        config(days=3, islanding_by_day=((5,), ()))


def test_the_days_islanding_is_one_seeded_event_of_whole_hours():
    assert draw_islanding(0, 1) == ()
    event = draw_islanding(3, 1)
    assert len(event) == 3 and event == tuple(range(event[0], event[0] + 3)) and 1 <= event[0] <= HOURS - 2
    assert draw_islanding(3, 1) == event
    assert draw_islanding(HOURS, 5) == tuple(range(1, HOURS + 1))


def test_schedules_stopped_short_are_listed_per_agent_and_day_with_their_gap_and_said_in_the_summary():
    """A schedule whose solve stopped short of its gap (a time limit) is never silent: each day lists it with its
    certified gap, a run of several days lists each with its market day, and the summary names them."""
    from dmo.operator.report import DayReport  # noqa: PLC0415
    from dmo.operator.results import RunResult, stopped_short  # noqa: PLC0415
    from dmosim.cli.run import summary_table  # noqa: PLC0415
    from dmosim.results.report import RunReport  # noqa: PLC0415
    from messages import Schedule  # noqa: PLC0415

    def schedule(agent: str, status: str, gap: float | None) -> Schedule:
        return Schedule(sender=agent, market_day="2026-07-01", status=status, commitment={"G1": [1] * HOURS},
                        expected_cost=100.0, p_m_expected_mw=[0.0] * HOURS, scenarios=3, mip_gap=gap)

    day = stopped_short({"mg2": schedule("mg2", "time_limit", 0.0113), "mg1": schedule("mg1", "optimal", 0.004),
                         "mg3": schedule("mg3", "interrupted", None)})
    assert [s.model_dump() for s in day] == [{"agent": "mg2", "status": "time_limit", "mip_gap": 0.0113},
                                             {"agent": "mg3", "status": "interrupted", "mip_gap": None}]
    settlement = {"mg1": {"energy_charge": 1.0, "deviation_penalty": 0.0, "credit": 0.0, "total": 1.0,
                          "award_mwh": 1.0, "import_mwh": 1.0, "deviation_mwh": 0.0, "missing_subperiods": 0}}
    totals = {"agents": ["mg1"], "energy_charge": 1.0, "deviation_penalty": 0.0, "credit": 0.0, "total": 1.0,
              "deviation_mwh": 0.0, "missing_subperiods": 0, "agents_without_meter": []}
    days = [DayReport.model_validate({
        "day": d, "market_day": f"2026-07-0{d}", "islanded_hours": [], "clearing_prices": [40.0] * HOURS,
        "congestion": ["none"] * HOURS, "awards": {"mg1": [0.0] * HOURS}, "settlement": settlement,
        "day_summary": totals, "expected_cost": {"mg1": 100.0}, "phase_s": {},
        "rejected_messages": 0, "rejected_by_code": {}, "accepted_messages": {}, "received_again": 0,
        "dropped_messages": {}, "locked_out": [], "incidents": [], "schedules_stopped_short": short})
        for d, short in ((1, day), (2, []))]
    run = RunResult(days, "paper", ["mg1"]).report("run-1", {})
    assert [s.model_dump() for s in run.schedules_stopped_short] == [
        {**s.model_dump(), "market_day": "2026-07-01"} for s in day]
    assert RunResult(days[:1], "paper", ["mg1"]).report("run-1", {}).schedules_stopped_short == day
    ran = {"experiment": "run", "wall_s": 1.0, "run_dir": "run", "logs": "run/logs", "recording": None,
           "faults": [], "restarts": {}, "verdict": {"ok": True, "problems": []}}
    text = summary_table(RunReport.model_validate({**dict(run), **ran}))
    assert ("schedules stopped short of their gap: 2 (mg2 2026-07-01 time_limit at gap 1.13%, "
            "mg3 2026-07-01 interrupted)") in text.splitlines()
    assert "stopped short" not in summary_table(
        RunReport.model_validate({**dict(RunResult(days[1:], "paper", ["mg1"]).report("run-1", {})), **ran}))
