"""Faults (docs/faults.md): message faults at the sender's Bus, duplicates and replays, delayed and
lost messages, agents that restart or may not join, a gap in the hours, and ``dmosim run --fault`` end to end.

The DMO runs in this process with scripted agents (no solver) where the protocol is under test, so those days
take a few seconds; one test runs the real processes. Every bus and process is closed in a ``finally``.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import json
import os
import queue
import random
import signal
import subprocess
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_market_day import DEADLINES, ENV, ROOT, TINY, dmosim, ended

from dmosim.cli import main as cli_main
from dmosim.launch.processes import free_port
from dmo.operator.config import LOGICAL, WALL, DayConfig
from dmo.operator.day import MarketDay
from messages import (HOURS, Bid, CallForBids, DaySummary, GridState, MessageError, MeterReport, Receipt,
                      Registration, Schedule, decode, encode)
from messages.keys import Keys, new_run_id
from dmo.replay.resettle import recording_days, resettled_differences
from messages.budget import BUDGET_BYTES, BUDGET_MESSAGES
from messages.recording import Recorder, RecordingWriter, read_recording
from messages.recording.layout import DROPPED_METADATA
from messages.transport import Bus, BusConfig
from messages.transport.faults import FaultInjector, FaultSpecError, MessageFault, corrupt, parse_message_fault
from microgrid_agent.agent.delivery import Delivery

DAY = "2026-07-01"
K = 2
AWARD = 1.0
CAP = 10.0


# --- fault specs and the injector ------------------------------------------------------------------------------

def test_fault_specs_parse_and_nonsense_is_refused_with_a_reason():
    assert parse_message_fault("drop:agent/*/meter:0.25") == MessageFault("drop", "agent/*/meter", 0.25)
    assert parse_message_fault("delay:dmo/grid:1.5") == MessageFault("delay", "dmo/grid", 1.0, 1.5)
    assert parse_message_fault("delay:agent/**:2:0.5") == MessageFault("delay", "agent/**", 0.5, 2.0)
    assert str(parse_message_fault("corrupt:agent/mg2/bid:1")) == "corrupt:agent/mg2/bid:1"
    for bad in ("drop:agent/*/meter", "drop:agent/*/meter:2", "drop:agent/*/meter:nan", "melt:agent/*:1",
                "delay:dmo/grid:-1", "delay:dmo/grid:1:0.5:9", "duplicate:agent/m+/meter:1", "drop::1",
                "corrupt:agent//meter:1", "drop:/agent:1"):
        with pytest.raises(FaultSpecError):
            parse_message_fault(bad)


def test_patterns_match_whole_key_levels_like_zenoh():
    assert MessageFault("drop", "agent/*/meter", 1).matches("agent/mg1/meter")
    assert not MessageFault("drop", "agent/*/meter", 1).matches("agent/mg1/bid")
    assert not MessageFault("drop", "agent/*", 1).matches("agent/mg1/meter")
    assert MessageFault("drop", "agent/**", 1).matches("agent/mg1/meter")
    assert MessageFault("drop", "**", 1).matches("dmo/award/mg1")
    assert MessageFault("drop", "dmo/**/mg1", 1).matches("dmo/award/mg1")
    assert not MessageFault("drop", "dmo/grid", 1).matches("dmo/grid2")
    assert MessageFault("drop", "dmo/award/mg*", 1).matches("dmo/award/mg12")  # as dmosim replay --topics


messages = st.builds(
    lambda hour, p_m, seq: MeterReport(sender="mg1", market_day=DAY, hour=hour, subperiods=len(p_m), p_m_mw=p_m,
                                       deviation_mw=tuple(x - 1.0 for x in p_m), seq=seq),
    st.integers(1, 24), st.lists(st.floats(-10, 10, allow_nan=False), min_size=1, max_size=6).map(tuple),
    st.integers(0, 10**6))


@settings(max_examples=300, deadline=None)
@given(msg=messages, seed=st.integers(0, 2**32))
def test_a_corrupted_payload_is_never_a_valid_message(msg, seed):
    payload = encode(msg)
    damaged = corrupt(payload, random.Random(seed))
    assert damaged != payload
    with pytest.raises(MessageError):
        decode(damaged)


def test_the_injector_is_seeded_never_blocks_and_counts_what_it_did():
    sent: list[tuple[str, bytes, float]] = []
    delayed = threading.Event()

    def put(key, payload):
        sent.append((key, payload, time.monotonic()))
        if key.endswith("schedule"):
            delayed.set()
    prefix = "dmosim/r1"
    faults = [parse_message_fault(s) for s in ("drop:agent/*/meter:0.3", "duplicate:agent/*/bid:1",
                                               "delay:agent/*/schedule:0.3", "corrupt:agent/mg1/register:1")]

    def run(seed):
        sent.clear()
        delayed.clear()
        inj = FaultInjector(faults, prefix, seed, "mg1")
        drops = []
        for hour in range(1, 25):
            before = len(sent)
            inj.send(f"{prefix}/agent/mg1/meter", b"m%d" % hour, put)
            drops.append(len(sent) == before)
        inj.send(f"{prefix}/agent/mg1/bid", b"bid", put)
        inj.send(f"{prefix}/agent/mg1/register", encode(Registration(sender="mg1", market_day=DAY, case="paper",
                                                                     max_import_mw=1.0, max_export_mw=1.0)), put)
        start = time.monotonic()
        inj.send(f"{prefix}/agent/mg1/schedule", b"schedule", put)
        assert time.monotonic() - start < 0.1  # the caller goes on; a timer thread sends it later
        assert not any(k.endswith("schedule") for k, _, _ in sent)
        assert delayed.wait(10), "the delayed schedule never went out"
        return drops, inj.summary(), list(sent)

    drops, counts, out = run(seed=7)
    assert (drops, counts) == run(seed=7)[:2]  # same seed, same faults
    assert counts["drop"] == sum(drops) and 0 < counts["drop"] < 24
    assert [p for k, p, _ in out if k.endswith("/bid")] == [b"bid", b"bid"]
    (register,) = [p for k, p, _ in out if k.endswith("/register")]
    with pytest.raises(MessageError):
        decode(register)
    (schedule,) = [t for k, _, t in out if k.endswith("/schedule")]
    assert schedule - max(t for k, _, t in out if not k.endswith("/schedule")) >= 0.25
    assert counts == {"drop": counts["drop"], "duplicate": 1, "corrupt": 1, "delay": 1}


# --- the DMO with scripted agents, in this process -------------------------------------------------------------

class ScriptedAgent:
    """A stand-in agent without a solver: it bids nothing, schedules nothing and meters its award plus ``excess``
    MW in every sub-period. ``before_meter(agent, hour)`` runs before each meter report is sent. Like a real agent
    it learns the run's token from the DMO's clock, sends each message again until its receipt comes (``resend_s``
    after the first send), and leaves once it has the day's summary."""

    def __init__(self, run_id: str, name: str, endpoint: str, excess: float = 0.5, faults=(), before_meter=None,
                 resend_s: float = 0.5, bid_day: str = DAY):
        self.name, self.excess, self.before_meter, self.bid_day = name, excess, before_meter, bid_day
        injector = (FaultInjector([parse_message_fault(f) for f in faults], Keys(run_id).prefix, 1, name)
                    if faults else None)
        self.bus = Bus(run_id, name, BusConfig(mode="client", connect=(endpoint,)), faults=injector).open()
        self.delivery = Delivery(self.bus.republish, first_s=resend_s)
        self.events: queue.Queue = queue.Queue()
        self.award = None
        self.pending: GridState | None = None
        self.metered = 0
        self.refusals: list[Receipt] = []
        self.summary = threading.Event()
        self.registered = threading.Event()  # like a real agent, it registers before it handles anything
        k = self.bus.keys
        for key in (k.call_for_bids(), k.award(name), k.grid(), k.summary()):
            self.bus.subscribe(key, lambda key, msg, at: self.events.put(msg))
        self.bus.subscribe(k.receipt(name), lambda key, msg, at: self._receipt(msg))
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def register(self) -> None:
        assert self.bus.wait_for_subscribers(self.bus.keys.register(self.name), 10)
        deadline = time.monotonic() + 10
        while not (clock := self.bus.fetch(self.bus.keys.clock(), timeout_s=1.0)):  # the DMO answers once it listens
            assert time.monotonic() < deadline, "the DMO never answered for its clock"
        self.bus.run_token = decode(clock[0][1]).run
        self.publish(Registration(sender=self.name, market_day=DAY, case="scripted", max_import_mw=CAP,
                                  max_export_mw=CAP))
        self.registered.set()

    def publish(self, msg) -> None:
        self.bus.publish(msg, before_put=self.delivery.sent)

    def _receipt(self, receipt: Receipt) -> None:
        if self.delivery.receipt(receipt) is not None and not receipt.accepted:
            self.refusals.append(receipt)

    def _loop(self) -> None:
        self.registered.wait()
        while (msg := self.events.get()) is not None:
            try:
                self._handle(msg)
            except RuntimeError:  # the bus was closed under it (a "restart"): this incarnation is over
                return

    def _handle(self, msg) -> None:
        if isinstance(msg, CallForBids):
            self.publish(Bid(sender=self.name, market_day=self.bid_day, hours=((),) * HOURS))
        elif msg.kind == "award" and self.award is None:
            self.award = msg
            self.publish(Schedule(sender=self.name, market_day=DAY, status="scripted", commitment={},
                                      expected_cost=0.0, p_m_expected_mw=msg.p_sch_mw, scenarios=1, mip_gap=0.0))
            if self.pending is not None:  # the grid state overtook the award
                self._meter(self.pending)
        elif isinstance(msg, GridState):
            if self.award is None:
                self.pending = msg
            elif msg.hour > self.metered:
                self._meter(msg)
        elif isinstance(msg, DaySummary):  # like a real agent, it leaves once what it sent is receipted
            self.delivery.drained(10)
            self.bus.close()
            self.summary.set()

    def _meter(self, grid: GridState) -> None:
        self.metered = grid.hour
        if self.before_meter is not None:
            self.before_meter(self, grid.hour)
        p_m = self.award.p_sch_mw[grid.hour - 1] + self.excess
        connected = grid.connected  # islanded: P_M = 0
        self.publish(MeterReport(sender=self.name, market_day=DAY, hour=grid.hour, subperiods=grid.subperiods,
                                 p_m_mw=tuple(p_m if up else 0.0 for up in connected),
                                 deviation_mw=tuple(self.excess if up else -p_m + self.excess for up in connected)))

    def close(self) -> None:
        self.registered.set()
        self.events.put(None)
        self.delivery.close()
        self.bus.close()


@contextlib.contextmanager
def scripted_day(agents=("mg1", "mg2"), hour_s=2.0, faults=None, before_meter=None, resend_s=0.5, journal=None,
                 recording=None, budget=(BUDGET_MESSAGES, BUDGET_BYTES), restarting=(), clock=WALL, phase_s=None,
                 bid_days=None):
    """A DMO (in a thread) and scripted agents; yields (day, agents, outcome) and closes everything on exit.
    ``outcome`` fills in with "result" (the DayResult) or "error" once the DMO's day is over. ``journal``: where the
    DMO journals; ``recording``: a file a recorder writes the day to (closed once the day is over); ``budget``: what
    one agent may send the DMO in a phase or hour (messages/budget.py); ``restarting``: the agents the run restarts;
    ``clock``: how a phase ends (dmo/operator/config.py), ``phase_s`` the deadline of every phase but the hours';
    ``bid_days``: agent -> the market day its bid names (else the day's)."""
    run_id, endpoint = new_run_id(), f"tcp/127.0.0.1:{free_port()}"
    config = DayConfig(market_day=DAY, agents=len(agents), iso_price=(50.0,) * HOURS, import_limit=100.0,
                       export_limit=100.0, penalty=150.0, credit=0.0, subperiods=K, islanded_hours=(7,),
                       fixed_awards=(AWARD,) * HOURS, registration_s=phase_s or 20.0, bids_s=phase_s or 10.0,
                       schedule_s=phase_s or 10.0, hour_s=hour_s, linger_s=1.0, journal=journal, budget=budget,
                       restarting=frozenset(restarting), clock=clock)
    outcome: dict = {}
    done = threading.Event()
    with contextlib.ExitStack() as stack:
        bus = stack.enter_context(Bus(run_id, "dmo", BusConfig(mode="router", listen=(endpoint,))))
        day = MarketDay(bus, config)

        def run():
            try:
                outcome["result"] = day.run().last
            except Exception as exc:  # noqa: BLE001  (reported by the test)
                outcome["error"] = exc
            done.set()

        if recording is not None:
            stack.enter_context(recorder_of(run_id, endpoint, recording, done))
        threading.Thread(target=run, daemon=True).start()
        scripted = {}
        for name in agents:
            scripted[name] = ScriptedAgent(run_id, name, endpoint, faults=(faults or {}).get(name, ()),
                                           before_meter=before_meter, resend_s=resend_s,
                                           bid_day=(bid_days or {}).get(name, DAY))
            stack.callback(lambda a=name: scripted[a].close())
        for a in scripted.values():
            a.register()
        outcome["endpoint"], outcome["run_id"], outcome["done"] = endpoint, run_id, done
        yield day, scripted, outcome
        assert done.wait(120), "the DMO's day did not end"


@contextlib.contextmanager
def recorder_of(run_id: str, endpoint: str, path, done: threading.Event):
    """A recorder of the run, in this process, that listens from before the DMO's day starts and closes ``path``
    once ``done`` is set (it announces nothing: the DMO does not wait for it to ask for what it missed)."""
    with Bus(run_id, "recorder", BusConfig(mode="client", connect=(endpoint,)), announce=False) as bus:
        recorder = Recorder(bus, RecordingWriter(path, run_id), announce=False)
        recorder.writer.start({"market_day": DAY, "days": "1"}, [])
        recorder.start(backfill=False)
        stop = threading.Event()
        loop = threading.Thread(target=recorder.run, args=(stop,))
        loop.start()
        try:
            yield recorder
        finally:
            done.wait(120)
            stop.set()
            loop.join(30)


def finished(outcome):
    assert outcome["done"].wait(120)
    assert "error" not in outcome, outcome.get("error")
    return outcome["result"]


def totals(result) -> dict:
    return {a: (str(st.total), st.missing_subperiods) for a, st in result.statements.items()}


@pytest.fixture(scope="module")
def baseline():
    """The scripted day undisturbed: what every fault below must leave unchanged where it does not lose data."""
    with scripted_day() as (day, agents, outcome):
        pass
    result = finished(outcome)
    assert result.state.rejected == 0 and result.state.accepted["meter_report"] == 2 * HOURS
    return result


def test_copies_change_nothing_and_replays_with_other_content_are_refused_once_each(baseline):
    captured: list[tuple[str, bytes]] = []
    copies, forged = [], []
    changed_payloads: set[bytes] = set()  # not captured for replay: only what the agents said is

    def replay_the_past(agent, hour):
        # Before its own report, the agent's bus plays back what this run's agents said before, byte for byte (each
        # an exact copy of an accepted message: it is receipted again and changes nothing), and once more with the
        # content changed but an old seq: replays, each refused as a duplicate.
        if agent.name != "mg1" or hour % 4:
            return
        for key, payload in list(captured):
            agent.bus.publish_raw(key, payload)
            copies.append(key)
            msg = decode(payload)
            if isinstance(msg, MeterReport) and msg.hour < hour:  # its seq was accepted already
                changed = encode(msg.model_copy(update={"hour": hour, "p_m_mw": (0.0,) * K,
                                                        "deviation_mw": (-AWARD,) * K}))
                changed_payloads.add(changed)
                agent.bus.publish_raw(key, changed)
                forged.append(key)

    faults = {"mg1": ["duplicate:agent/**:1"], "mg2": ["duplicate:agent/*/meter:0.5"]}
    # the replays of the whole day so far are more than an agent may send in an hour: this test is of copies and
    # replays, each decided; the budget has its own test (below)
    budget = (100 * BUDGET_MESSAGES, 100 * BUDGET_BYTES)
    with scripted_day(faults=faults, before_meter=replay_the_past, budget=budget) as (day, agents, outcome):
        tap = Bus(outcome["run_id"], "tap", BusConfig(mode="client", connect=(outcome["endpoint"],)), announce=False)
        with tap.open():
            seen = set()

            def keep(key, payload, at):
                if payload not in seen and payload not in changed_payloads and "/agent/" in key:
                    seen.add(payload)
                    captured.append((key, payload))

            tap.subscribe_raw(tap.keys.agent_all("*"), keep)
            assert outcome["done"].wait(120)
    result = finished(outcome)
    injected = sum(a.bus.faults.summary().get("duplicate", 0) for a in agents.values())
    resent = sum(a.delivery.resent for a in agents.values())
    s = result.state
    assert injected >= 27 and copies and forged
    # every copy (injected, replayed, or sent again for want of a receipt) was taken as its message again
    assert injected + len(copies) <= s.again <= injected + len(copies) + resent
    assert s.rejected == len(forged) and set(s.rejected_by_code) == {"duplicate"}
    assert s.accepted == baseline.state.accepted  # nothing counted twice, nothing lost
    assert totals(result) == totals(baseline)
    print(f"\nscripted day: {injected} duplicates and {len(copies)} copies taken again, {len(forged)} replays with "
          "other content rejected as duplicate; settlement unchanged")


def test_a_meter_report_delayed_past_its_hour_is_rejected_as_late_and_settled_as_missing(baseline):
    # (no resends: a report sent again would overtake the delayed one, which is what resends are for)
    with scripted_day(hour_s=0.5, faults={"mg2": ["delay:agent/mg2/meter:0.8:0.3"]}, resend_s=3600) as (day, agents,
                                                                                                      outcome):
        pass
    result = finished(outcome)
    delayed = agents["mg2"].bus.faults.summary()["delay"]
    st_ = result.statements
    assert 0 < delayed < HOURS
    assert st_["mg2"].missing_subperiods == K * delayed
    assert totals(result)["mg1"] == totals(baseline)["mg1"]
    # each delayed report arrived in a later hour (or after the day): refused as late, never counted
    assert set(result.state.rejected_by_code) <= {"late"} and result.state.rejected <= delayed
    assert result.state.accepted["meter_report"] == 2 * HOURS - delayed
    assert sum(1 for i in result.state.incidents if "late" in i.reason and i.agent == "mg2") >= delayed


def test_on_the_logical_clock_no_deadline_makes_an_answer_late_so_the_day_settles_as_undisturbed(baseline):
    """Every deadline a hundredth of a second and mg2's meter reports held back 0.3 s (held, not lost: nothing sends
    them again) in 80% of hours: on the wall clock they are late and settled as missing (the test above); on the
    logical clock each phase and hour waits for every live agent, and the day is the undisturbed one."""
    with scripted_day(hour_s=0.01, phase_s=0.01, clock=LOGICAL, faults={"mg2": ["delay:agent/mg2/meter:0.8:0.3"]},
                      resend_s=3600) as (day, agents, outcome):
        pass
    result = finished(outcome)
    assert agents["mg2"].bus.faults.summary()["delay"] > 0
    assert result.state.rejected == 0 and result.state.accepted == baseline.state.accepted
    assert not [i for i in result.state.incidents if i.agent is not None]
    assert totals(result) == totals(baseline)


def test_on_the_logical_clock_an_answer_refused_ends_the_wait_for_it(baseline):
    """mg2 bids for another market day: refused, and (told no) it does not send its bid again. The logical clock has no
    deadline to end the bidding phase, so the refusal does: the day goes on without mg2's bid and settles. (A payload
    that arrives corrupt is no answer: its sender cannot tell the refusal is for it, and sends it again.)"""
    with scripted_day(clock=LOGICAL, bid_days={"mg2": "2026-07-02"}) as (day, agents, outcome):
        pass
    result = finished(outcome)
    assert [r.code for r in agents["mg2"].refusals] == ["wrong_day"]
    assert result.state.rejected == 1 and result.state.accepted["bid"] == 1 and "mg2" not in result.state.bids
    assert {i.agent for i in result.state.incidents} == {"mg2"}  # its refusal, and no one late
    assert result.state.accepted["meter_report"] == 2 * HOURS and totals(result) == totals(baseline)


def test_an_agent_flooding_the_dmo_is_held_to_its_budget_and_costs_no_one_else_anything(baseline, tmp_path):
    """At hour 3, mg1 sends 60 junk payloads of 256 KiB, 60 refused registrations and 60 copies of one payload, all
    on its own keys, then its meter report. The DMO and the recorder take 32 messages and 128 KiB of it in that
    hour (messages/budget.py) and drop the rest unread: mg1's own report of the hour among them (it is missing, as are
    those of the hours its flood overran: an agent over its budget is not waited for),
    nothing of the junk in the journal, a recording that reads and re-settles, and mg2's bill as undisturbed."""
    junk = b"\xff" * (256 << 10)

    def flood(agent, hour):
        if agent.name != "mg1" or hour != 3:
            return
        k = agent.bus.keys
        for _ in range(60):
            agent.bus.publish_raw(k.meter(agent.name), junk)
        for _ in range(60):  # distinct seqs: each one valid, and refused (registration is over)
            agent.bus.publish(Registration(sender=agent.name, market_day=DAY, case="scripted", max_import_mw=CAP,
                                           max_export_mw=CAP))
        copy = agent.bus.publish(Registration(sender=agent.name, market_day=DAY, case="scripted", max_import_mw=CAP,
                                              max_export_mw=CAP))
        for _ in range(60):  # a resend storm of one payload
            agent.bus.republish(k.register(agent.name), encode(copy))

    journal, recording = tmp_path / "dmo.journal", tmp_path / "day.mcap"
    with scripted_day(before_meter=flood, journal=str(journal), recording=recording) as (day, agents, outcome):
        pass
    result = finished(outcome)
    assert totals(result)["mg2"] == totals(baseline)["mg2"]
    # its hour-3 report came after its budget was spent; and an agent over its budget is not waited for, so the hours
    # its flood overran went on without it too
    assert K <= result.statements["mg1"].missing_subperiods < HOURS * K and result.state.meter["mg1"].get(HOURS - 1)
    assert result.state.dropped["mg1"] >= 3 * 60 + 1 - BUDGET_MESSAGES and set(result.state.dropped) == {"mg1"}
    # what it got through was refused, and no more: a budget's worth in each window its flood reached (the hours of
    # its incidents)
    windows = {(i.phase, i.hour) for i in result.state.incidents if i.agent == "mg1"}
    assert result.state.rejected <= BUDGET_MESSAGES * len(windows), (result.state.rejected, windows)
    assert journal.stat().st_size < 1 << 20  # of 15 MiB of junk, none

    rec = read_recording(recording)  # within the reader's budget, whatever mg1 sent
    assert resettled_differences(rec, recording_days(rec)) == []
    assert 0 < int(rec.other_metadata[DROPPED_METADATA]["mg1"]) <= 3 * 60 + 1
    assert recording.stat().st_size < 1 << 20
    print(f"\nflooded day: the DMO dropped {result.state.dropped['mg1']} of mg1's payloads and refused "
          f"{result.state.rejected}; journal {journal.stat().st_size:,} bytes, recording {recording.stat().st_size:,}")


@pytest.mark.parametrize("noticed", [True, False], ids=["after-it-vanished", "before-it-is-noticed"])
def test_a_restarted_agent_rejoins_gets_its_award_again_and_reports_on(baseline, noticed):
    """The new process registers once the DMO has seen the old one vanish, or at once: the agent's identity is its
    credentials and its later incarnation, not what the DMO saw of its presence."""
    restarted, back = {}, threading.Event()

    def crash(agent, hour):
        if agent.name == "mg2" and hour == 5 and not restarted:
            restarted["old"] = agent
            raise RuntimeError("mg2 crashes before reporting hour 5")
        if agent.name == "mg1" and hour > 5:  # alone, mg1 would drive the day to its end before mg2 is back
            back.wait(30)

    with scripted_day(hour_s=5.0, before_meter=crash) as (day, agents, outcome):
        deadline = time.monotonic() + 30
        while "old" not in restarted and time.monotonic() < deadline:
            time.sleep(0.01)
        if noticed:
            restarted["old"].close()  # the process is gone: its liveliness token with it
            while "mg2" not in day.state.vanished and time.monotonic() < deadline:
                time.sleep(0.01)
        time.sleep(3); new = ScriptedAgent(outcome["run_id"], "mg2", outcome["endpoint"])  # a new process: seq from 0
        try:
            new.register()
            back.set()
            if not noticed:
                restarted["old"].close()  # the old process goes only now, after the new one registered
            assert new.summary.wait(60)
        finally:
            new.close()
    result = finished(outcome)
    reasons = [i.reason for i in result.state.incidents if i.agent == "mg2"]
    assert any("vanished" in r for r in reasons) == noticed  # an old token that goes while a new one is there: no
    assert any(r.startswith("rejoined") and "sent its award" in r for r in reasons)
    assert result.locked_out == ()
    (rejoined,) = [i.hour for i in result.state.incidents if i.agent == "mg2" and i.reason.startswith("rejoined")]
    missing = [line.hour + 1 for line in result.statements["mg2"].lines if line.missing]
    assert missing == list(range(5, rejoined))  # from the hour it crashed in until the hour it rejoined in
    assert result.state.accepted["meter_report"] == 2 * HOURS - len(missing)
    assert result.state.rejected == 0
    assert totals(result)["mg1"] == totals(baseline)["mg1"]


def test_an_agent_the_run_restarts_is_waited_for_while_its_new_process_starts(baseline):
    """mg2 dies before reporting hour 5 and its new process registers 3 s later. The run restarts it, so the DMO
    waits for it (within the hour's deadline) instead of running the day on with mg1 alone, which answers at once:
    it rejoins in hour 5, is sent that hour's grid state, and reports every hour."""
    died = {}

    def crash(agent, hour):
        if agent.name == "mg2" and hour == 5 and not died:
            died["old"] = agent
            raise RuntimeError("mg2 crashes before reporting hour 5")

    with scripted_day(hour_s=8.0, before_meter=crash, restarting=("mg2",)) as (day, agents, outcome):
        deadline = time.monotonic() + 30
        while "old" not in died and time.monotonic() < deadline:
            time.sleep(0.01)
        died["old"].close()
        while "mg2" not in day.state.vanished and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(3); new = ScriptedAgent(outcome["run_id"], "mg2", outcome["endpoint"])  # a new process starting
        try:
            new.register()
            assert new.summary.wait(60)
        finally:
            new.close()
    result = finished(outcome)
    (rejoined,) = [i.hour for i in result.state.incidents if i.agent == "mg2" and i.reason.startswith("rejoined")]
    assert rejoined == 5 and result.statements["mg2"].missing_subperiods == 0
    assert totals(result) == totals(baseline)


def test_an_agent_that_may_not_join_is_told_why_and_exits_1(tmp_path):
    from dmosim.experiment.spec import Experiment  # noqa: PLC0415
    from dmosim.launch.roles import agent_config, member_of  # noqa: PLC0415
    from microgrid_agent.agent.machine import AgentRefused  # noqa: PLC0415
    from microgrid_agent.agent.process import MicrogridAgent  # noqa: PLC0415
    from scenarios.case import load_case  # noqa: PLC0415

    reached = threading.Event()

    def wait_at_hour_3(agent, hour):
        if hour == 3 and agent.name == "mg1":
            reached.set()
            time.sleep(1.0)

    with scripted_day(hour_s=5.0, before_meter=wait_at_hour_3) as (day, agents, outcome):
        assert reached.wait(60)
        with Bus(outcome["run_id"], "mg9", BusConfig(mode="client", connect=(outcome["endpoint"],))) as bus:
            config = dataclasses.replace(agent_config(Experiment(), member_of(Experiment(), "mg1")), idle_s=30)
            late = MicrogridAgent(bus, load_case("paper"), config, DAY)
            with pytest.raises(AgentRefused, match=r"mg9: the DMO refused the registration \(late\): registration "
                                                   r"is closed \(now realtime\): mg9 is not an agent of this day"):
                late.run()
    result = finished(outcome)
    assert result.state.rejected_by_code == {"late": 1} and "mg9" not in result.state.registered


# --- the agent: a gap in the hours, repeated DMO messages ----------------------------------------------------

def test_the_operator_catches_up_missed_hours_in_one_lp_and_the_day_stays_valid():
    from microgrid_agent.agent.realtime import Operator  # noqa: PLC0415
    from microgrid_agent.checker import check_schedule  # noqa: PLC0415
    from microgrid_agent.model import (
        Params,  # noqa: PLC0415
        first_stage_of,  # noqa: PLC0415
    )
    from microgrid_agent.solvers.extensive import solve  # noqa: PLC0415
    from scenarios.case import load_case  # noqa: PLC0415
    from scenarios.generation import make_scenarios, sample  # noqa: PLC0415

    case = load_case("paper")
    p_sch = np.asarray(case.grid.p_sch, float)
    schedule = solve(case, make_scenarios(case, 1, 1, island_hours=1, seed=0), Params(p_sch, 150.0), gap=0.01)
    op = Operator(case, first_stage_of(schedule), p_sch, 150.0, 1, sample(case, 1, 1, island_hours=0, seed=3))
    op.operate_hour(1, [True])
    assert op.catch_up(2) == () and op.next_hour == 2
    caught = op.catch_up(9, {4: [False]})  # hours 2..8, hour 4 known islanded
    assert [h.hour for h in caught] == list(range(2, 9)) and op.next_hour == 9
    assert caught[2].p_m[0] == 0.0  # islanded: no transfer
    with pytest.raises(ValueError, match="in order"):
        op.operate_hour(12, [True])
    op.operate_hour(9, [True])
    op.catch_up(25)
    day = op.day_result()
    check_schedule(case, day.scenario, day.schedule, p_sch=p_sch, penalty=150.0).raise_if_failed()


# --- real processes: dmosim run --fault ---------------------------------------------------------------------

def test_dmosim_run_survives_message_faults_and_a_restart_and_settles_what_it_accepted(tmp_path):
    # the grid state's delay paces the hours, so that the restarted agent (seconds to start) rejoins mid-day
    faults = ["duplicate:agent/*/meter:1", "duplicate:dmo/grid:1", "delay:dmo/grid:0.5", "corrupt:agent/mg2/meter:0.15",
              "drop:agent/mg1/meter:0.1", "delay:agent/*/bid:0.3", "restart:mg1:2",
              "drop:dmo/statement/mg2:1", "drop:dmo/summary:1"]  # asked for by the agent, caught up by the recorder
    deadlines = [*DEADLINES[:-1], "2.5"]
    assert DEADLINES[-2] == "--hour-timeout"
    argv = dmosim("run", "--agents", "2", "--subperiods", "1", *TINY, *deadlines, "--out", str(tmp_path), "--json",
                  "--seed", "3", *[flag for f in faults for flag in ("--fault", f)])
    out = ended(argv, timeout=600, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout)
    assert result["faults"] == faults and result["restarts"] == {"mg1": 1}
    assert "fault: restarting mg1" in out.stderr

    # the DMO refused every duplicate and corruption, with its reason, and counted each once
    by_code = result["rejected_by_code"]
    assert result["received_again"] >= 20 and sum(by_code.values()) == result["rejected_messages"]
    assert set(by_code) <= {"not_json", "invalid", "late"} and result["locked_out"] == []
    # a corrupted or dropped report was sent again until its receipt came: none was lost
    assert result["settlement"]["mg2"]["missing_subperiods"] == 0
    # no accepted meter report lost: every hour not settled as missing is one accepted report
    settled = sum(HOURS - s["missing_subperiods"] for s in result["settlement"].values())
    assert settled == result["accepted_messages"]["meter_report"]
    incidents = [i for i in result["incidents"] if i["agent"] == "mg1"]
    assert any("vanished" in i["reason"] for i in incidents)
    assert any(i["reason"].startswith("rejoined") for i in incidents)
    assert result["settlement"]["mg1"]["missing_subperiods"] < 20  # it came back and reported again

    # the recording alone re-settles to the same statements, the refused reports left out
    assert cli_main(["settle", result["recording"]]) == 0
    assert result["recorded"]["complete"]
    counts = result["realised"]["mg1"]  # what its realised day says of the process that operated it
    # the restarted agent took up the day at a later hour's grid state and caught up on the hours before, unreported
    assert min(e["hour"] for e in counts[-1]["compute"] if e["kind"] == "grid_state") > 1
    assert counts and counts[-1]["messages"]["ignored"].get("grid_state_of_an_operated_hour", 0) >= 1  # duplicates
    injected = collections.Counter(result["transport"].get("faults_injected", {}))
    for agent in ("mg1", "mg2"):  # the process that operated each one's day to its end
        injected.update(result["realised"][agent][-1]["messages"]["faults_injected"])
    missing = {a: s["missing_subperiods"] for a, s in result["settlement"].items()}
    print(f"\ndmosim run faults: injected {dict(injected)} and 1 agent restart; DMO rejected "
          f"{result['rejected_messages']} {by_code}; missing hours {missing}; settle on the recording: identical")


def test_the_dmo_killed_mid_day_resumes_from_its_journal_and_settles_as_if_undisturbed(tmp_path):
    """SIGKILL the DMO half a second into hour 8 and start it again: it reads back its journal, waits for the agents
    to reconnect, runs hour 8 again; the agents send again the answers the dead DMO never got (their reports are
    delayed, so that hour 8's are on their way when it dies). Run beside the same day undisturbed, same seed."""
    common = ["run", "--agents", "2", "--subperiods", "1", *TINY, *DEADLINES, "--json", "--quiet", "--seed", "5"]
    runs = {}
    for name, faults in (("restarted", ["restart:dmo:8", "delay:agent/*/meter:0.6"]), ("undisturbed", [])):
        argv = dmosim(*common, "--out", str(tmp_path / name), *[x for f in faults for x in ("--fault", f)])
        runs[name] = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                      env=ENV, start_new_session=True)
    try:
        out = {name: p.communicate(timeout=600) for name, p in runs.items()}
    finally:
        for p in runs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    for name, p in runs.items():
        assert p.returncode == 0, f"{name}: {out[name][1][-3000:]}"
    restarted, undisturbed = (json.loads(out[name][0]) for name in ("restarted", "undisturbed"))
    assert restarted["restarts"] == {"dmo": 1}
    assert restarted["settlement"] == undisturbed["settlement"] and restarted["awards"] == undisturbed["awards"]
    assert restarted["accepted_messages"] == undisturbed["accepted_messages"]  # nothing lost, nothing twice
    (resumed,) = [i for i in restarted["incidents"] if "resumed day 1" in i["reason"]]
    assert resumed["hour"] == 8 and "not back" not in resumed["reason"]
    resent = sum(restarted["realised"][a][-1]["messages"]["sent_again"] for a in ("mg1", "mg2"))
    assert resent >= 1  # hour 8's reports, lost with the DMO, went again
    assert cli_main(["settle", restarted["recording"]]) == 0
    print(f"\nDMO restart: resumed at hour {resumed['hour']}, {resent} answer(s) sent again by the agents; settlement "
          f"identical to the undisturbed day: {restarted['settlement'] == undisturbed['settlement']}")


def test_the_dmo_and_an_agent_restarted_in_the_same_hour_and_across_midnight_lock_no_one_out(tmp_path):
    """The DMO and mg1 killed and started again in the same hour, on day 1 at hour 10 and again at hour 24 (the
    new mg1 rejoins in day 1's last hour, its settlement, or day 2's bidding): each resumed DMO takes mg1's new
    process back, mg1 takes part in all of day 2, and the run says it can be trusted (exit 0)."""
    # each hour's grid state half a second late: an hour lasts long enough for a restarted mg1 to start (seconds)
    # and rejoin in day 1, where its hours otherwise take milliseconds
    faults = ["restart:dmo:10", "restart:mg1:10", "restart:dmo:24", "restart:mg1:24", "delay:dmo/grid:0.5"]
    argv = dmosim("run", "--agents", "2", "--subperiods", "1", "--days", "2", *TINY, *DEADLINES[:-1], "10",
                  "--out", str(tmp_path), "--json", "--quiet", "--seed", "2",
                  *[flag for f in faults for flag in ("--fault", f)])
    out = ended(argv, timeout=600, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout)
    assert result["restarts"] == {"dmo": 2, "mg1": 2} and result["locked_out"] == []
    assert "duplicate" not in result["rejected_by_code"] and "unregistered" not in result["rejected_by_code"]
    day_2 = result["days"][1]["settlement"]
    assert day_2["mg1"]["missing_subperiods"] == 0 and day_2["mg2"]["missing_subperiods"] == 0
    rejoined = [i for i in result["incidents"] if i["agent"] == "mg1" and i["reason"].startswith("rejoined")]
    assert len(rejoined) == 2, result["incidents"]
    # back in the market within an hour of rejoining: the new process reports every later hour of day 1 until
    # it is killed in turn at hour 24
    reported = {m.hour for _, m in read_recording(result["recording"]).decoded("meter_report")
                if m.sender == "mg1" and m.market_day == result["market_days"][0]}
    first = rejoined[0]
    assert first["market_day"] == result["market_days"][0] and first["phase"] == "realtime"
    assert set(range(first["hour"] + 1, HOURS)) <= reported, (first, sorted(reported))
    assert cli_main(["settle", result["recording"]]) == 0
    missing = result["days"][0]["settlement"]["mg1"]["missing_subperiods"]
    print(f"\nDMO and mg1 restarted together twice: mg1 missing {missing} hour(s) of day 1, none of day 2; refused "
          f"{result['rejected_by_code']}")
