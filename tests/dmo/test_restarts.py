"""Restarts of the DMO and of agents, in any order and phase, across midnight, with messages and receipts lost: a
property test over random schedules of them, driving the DMO's own machine (``dmo/operator/machine.py``) without a
network; a DMO restart is a new machine on the journal the old one's actions wrote.

The simulated agents behave as dmosim's do (docs/protocol.md): every payload is sent again, the same bytes, until
its receipt comes; a process sends nothing before its registration's receipt; a restarted process registers again
and answers what the DMO sends it on rejoining. A restart is instantaneous here (the new process is up within the
same step, and the DMO sees no presence change), so every agent is up for every hour: no agent is ever locked out,
every hour of every agent is settled from the report its process metered, nothing its processes sent is refused but
what a process that is gone sent, and a resumed DMO holds everything it had receipted.
"""

from __future__ import annotations

import itertools
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dmo.operator.actions import CheckPresence, Journaled, OpenWindow, Publish, Settled, Stop, Wait
from dmo.operator.config import LOGICAL, DayConfig
from dmo.operator.events import Dropped, Left, Present, Received, TimedOut
from dmo.operator.journal import Journal
from dmo.operator.machine import DmoMachine
from messages import (Award, Bid, BidStep, CallForBids, Clock, GridState, MeterReport, Receipt, Registration,
                      Schedule, decode, encode, sha256)

DAYS = ("2026-07-01", "2026-07-02")
HOURS = 24
AGENTS = ("mg1", "mg2")
CAP = 10.0
RUN_ID = "restarts"
CONFIG = DayConfig(market_day=DAYS[0], agents=len(AGENTS), iso_price=(50.0,) * HOURS, import_limit=100.0,
                   export_limit=100.0, penalty=150.0, credit=0.0, subperiods=1, islanded_hours=(),
                   fixed_awards=(1.0,) * HOURS, registration_s=60.0, bids_s=60.0, schedule_s=60.0, hour_s=60.0,
                   days=len(DAYS), clock=LOGICAL)


def steps() -> list[tuple[int, str, int | None]]:
    """The DMO's clock over the run where it waits for the agents: (day, phase, hour). (Clearing and settlement
    wait for nobody: a restart right after midnight is one at the next day's bidding.)"""
    out = [(1, "registration", None)]
    for day in range(1, len(DAYS) + 1):
        out += [(day, "bidding", None), (day, "scheduling", None)]
        out += [(day, "realtime", hour) for hour in range(1, HOURS + 1)]
    return out


STEPS = steps()


def metered(agent: str, day: int, hour: int) -> float:
    """What the agent meters in an hour, whichever of its processes operates it."""
    return round((1 if agent == "mg1" else -1) * (0.1 * hour + day), 3)


class Dmo:
    """The DMO's machine and its journal; a restart is a new Dmo on the journal. Its requests for presence and a
    budget window are answered at once (every agent is up; nobody is over budget); ``give`` hands it an event and
    returns what it published meanwhile."""

    def __init__(self, path: Path, token: str):
        self.journal = Journal(path, RUN_ID, DAYS[0])
        self.machine = DmoMachine(CONFIG, token, self.journal.entries)
        self.resumed = self.machine.resumed
        self.clock: Clock | None = None
        self.settled: list[dict] = []
        self.published: list = []
        self.request = self._do(self.machine.start(0.0))

    @property
    def state(self):
        return self.machine.state

    @property
    def step(self) -> tuple[int, str, int | None]:
        return self.clock.day, self.clock.phase, self.clock.hour

    def give(self, event) -> list:
        """Hand the machine ``event``; what it published meanwhile."""
        start = len(self.published)
        self.request = self._do(self.machine.handle(event, 0.0))
        return self.published[start:]

    def _do(self, actions):
        while True:
            *done, request = actions
            for action in done:
                if isinstance(action, Publish):
                    self.published.append(action.msg)
                    if isinstance(action.msg, Clock):
                        self.clock = action.msg
                elif isinstance(action, Journaled):
                    self.journal.write(action.entry)
                elif isinstance(action, Settled):
                    self.settled.append(action.report)
            if isinstance(request, OpenWindow):
                actions = self.machine.handle(Dropped({}), 0.0)
            elif isinstance(request, CheckPresence):
                actions = self.machine.handle(Present(frozenset(request.names)), 0.0)
            elif isinstance(request, Wait) and request.until == -float("inf"):
                actions = self.machine.handle(TimedOut(), 0.0)  # nothing is queued: the agents send as they step
            else:
                return request


class Agent:
    """One agent's processes: the live one's numbering, its payloads awaiting a receipt, what it answered."""

    def __init__(self, name: str, token: str):
        self.name, self.token, self.incarnation = name, token, 0
        self.stragglers: list[tuple[str, bytes]] = []  # what a dead process had on the wire
        self.refused: list[str] = []
        self.start(DAYS[0])

    def start(self, market_day: str) -> None:
        self.incarnation += 1_000
        self.seq, self.pending, self.registered, self.answered, self.plan = 0, {}, False, set(), None
        self.send(Registration(sender=self.name, market_day=market_day, case="paper", max_import_mw=CAP,
                               max_export_mw=CAP), "register")

    def restart(self, market_day: str) -> None:
        self.stragglers += list(self.pending.values())
        self.start(market_day)

    def send(self, msg, topic: str) -> None:
        stamped = msg.model_copy(update={"run": self.token, "incarnation": self.incarnation, "seq": self.seq})
        payload = encode(stamped)
        self.pending[sha256(payload)] = (f"agent/{self.name}/{topic}", payload)
        self.seq += 1

    def answer(self, day: int, phase: str, hour: int | None) -> None:
        """What the live process sends in this step, once registered: its bid, schedule or the hour's report."""
        if not self.registered:
            return
        market_day = DAYS[day - 1]
        if phase == "bidding" and (day, "bid") not in self.answered:
            step = BidStep(price_per_mwh=40.0, quantity_mw=1.0)
            self.send(Bid(sender=self.name, market_day=market_day, hours=((step,),) * 24), "bid")
            self.answered.add((day, "bid"))
        if phase in ("scheduling", "realtime") and (day, "schedule") not in self.answered:
            self.send(Schedule(sender=self.name, market_day=market_day, status="optimal", commitment={},
                               expected_cost=0.0, p_m_expected_mw=(1.0,) * 24, scenarios=1, mip_gap=0.0),
                      "schedule")
            self.answered.add((day, "schedule"))
        if phase == "realtime" and (day, hour) not in self.answered:
            p_m = metered(self.name, day, hour)
            self.send(MeterReport(sender=self.name, market_day=market_day, hour=hour, subperiods=1, p_m_mw=(p_m,),
                                  deviation_mw=(p_m - 1.0,)), "meter")
            self.answered.add((day, hour))

    def receipt(self, kind: str) -> None:
        """The receipt of a payload came. That of the registration lets the process go on; a rejoined one answers
        what the DMO sent it on rejoining (``plan``) at once: a call for bids with its bid, the award with its
        schedule, a grid state with that hour's report, and nothing else of that phase or hour."""
        if kind != "registration" or self.registered:
            return
        self.registered = True
        if self.plan is None:
            return
        kinds, day, phase, hour = self.plan
        if phase == "bidding" and "call_for_bids" not in kinds:
            self.answered.add((day, "bid"))
        if phase == "realtime":
            if "grid_state" in kinds:
                self.answer(day, phase, hour)
            self.answered.add((day, hour))


def deliver(agent: Agent, dmo: Dmo, lost) -> None:
    """One round: each payload awaiting its receipt is sent (again); the payload or its receipt may be lost."""
    for sha, (key, payload) in sorted(agent.pending.items(), key=lambda item: decode(item[1][1]).seq):
        msg = decode(payload)
        if not agent.registered and msg.kind != "registration":
            continue  # nothing before the registration's receipt
        if next(lost):
            continue  # lost on the way: sent again next round
        # a new process's registration of a registered agent (not a copy of the one taken)
        rejoining = (isinstance(msg, Registration) and msg.sender in dmo.state.registered
                     and msg.incarnation != dmo.state.guard.incarnation.get(msg.sender))
        published = dmo.give(Received(f"dmosim/{RUN_ID}/{key}", msg, payload))
        (receipt,) = [m for m in published if isinstance(m, Receipt) and m.payload_sha256 == sha]
        if not receipt.accepted:
            agent.refused.append(f"{msg.kind} #{msg.seq}: {receipt.code}: {receipt.reason}")
        elif rejoining:  # what the DMO sent it on rejoining, whether or not the receipt gets through
            kinds = {m.kind for m in published if isinstance(m, (CallForBids, GridState))
                     or (isinstance(m, Award) and m.agent == agent.name)}
            agent.plan = (kinds, *dmo.step)
        if next(lost):
            continue  # the receipt is lost: the payload goes again
        del agent.pending[sha]
        if receipt.accepted:
            agent.receipt(msg.kind)


def run(schedule: dict[int, list[tuple[str, int]]], drops: list[bool], stragglers: bool, journal: Path,
        outages: frozenset[tuple[int, int, str]] = frozenset()) -> dict:
    """The run under ``schedule`` (step index -> [(who restarts, after how many delivery rounds)]), with each
    delivery lost as ``drops`` say in turn, and agents cut off in the rounds ``outages`` name (step index, round,
    agent): what each day settled (day -> agent -> {hour: MWh, of the hours not settled as missing}), and what was
    refused to whom."""
    token = "ab" * 16
    dmo = Dmo(journal, token)
    agents = {a: Agent(a, token) for a in AGENTS}
    lost = itertools.chain(drops, itertools.repeat(False))
    statements: list = []
    at, rounds = None, 0
    while not isinstance(dmo.request, Stop):
        if dmo.request.what == "their leaving":  # every agent has its summary, and leaves
            dmo.give(Left(dmo.request.waiting[0]))
            continue
        if dmo.step != at:
            at, rounds = dmo.step, 0
        day, phase, hour = at
        index = STEPS.index(at)
        for who, _ in [e for e in schedule.get(index, []) if e[1] == rounds]:
            if who == "dmo":
                receipted = {a: dict(m) for a, m in dmo.state.meter.items()}
                statements += [m for m in dmo.published if m.kind == "settlement_statement"]
                dmo.journal.close()
                dmo = Dmo(journal, token)  # resumed where it was, with all it receipted, and runs the step again
                assert dmo.resumed == (phase, hour) and dmo.state.day == day
                assert dmo.state.meter == receipted and dmo.step == at
            else:
                agents[who].restart(DAYS[day - 1])
        assert rounds < 200, f"step {at} never ends: waiting for {dmo.request.waiting}"
        for agent in agents.values():
            if isinstance(dmo.request, Stop) or dmo.request.what == "their leaving":
                break
            agent.answer(*dmo.step)  # the step it sees now: one that ended in this round has moved on
            if (index, rounds, agent.name) not in outages:
                deliver(agent, dmo, lost)
            for key, payload in agent.stragglers if stragglers else ():
                # a dead process's message arrives late: taken if its successor has not registered yet (the DMO
                # cannot tell it is dead), else refused
                published = dmo.give(Received(f"dmosim/{RUN_ID}/{key}", decode(payload), payload))
                (receipt,) = [m for m in published if isinstance(m, Receipt)
                              and m.payload_sha256 == sha256(payload)]
                assert receipt.accepted or receipt.code in ("stale", "wrong_day"), receipt
            agent.stragglers.clear()
        rounds += 1
    dmo.journal.close()
    assert not dmo.state.guard.locked_out()
    settled: dict[int, dict] = {}
    for statement in statements + [m for m in dmo.published if m.kind == "settlement_statement"]:
        settled.setdefault(DAYS.index(statement.market_day) + 1, {})[statement.agent] = {
            line.hour - 1: (line.import_mwh,) for line in statement.lines if not line.missing}
    return {"settled": settled, "refused": {a: agent.refused for a, agent in agents.items()}}


restart_schedules = st.dictionaries(
    st.integers(0, len(STEPS) - 1),
    st.lists(st.tuples(st.sampled_from(("dmo", *AGENTS)), st.integers(0, 3)), min_size=1, max_size=3),
    max_size=4)


outage_sets = st.frozensets(st.tuples(st.integers(0, len(STEPS) - 1), st.integers(0, 3), st.sampled_from(AGENTS)),
                            max_size=6)


@pytest.mark.slow  # a search of 300 schedules, seconds long: the cases below are the fast tier's
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(schedule=restart_schedules, drops=st.lists(st.booleans(), max_size=80), stragglers=st.booleans(),
       outages=outage_sets)
def test_no_restart_schedule_locks_an_agent_out_or_loses_an_hour_it_reported(schedule, drops, stragglers, outages):
    with tempfile.TemporaryDirectory() as tmp:
        out = run(schedule, drops, stragglers, Path(tmp) / "journal.jsonl", outages)
    for day in range(1, len(DAYS) + 1):
        for agent in AGENTS:
            assert out["settled"][day][agent] == {h - 1: (metered(agent, day, h),) for h in range(1, HOURS + 1)}
    assert out["refused"] == {a: [] for a in AGENTS}  # a live process is never refused


def test_the_issue_s_case_dmo_and_agent_restarted_in_the_same_hour_with_its_rejoin_lost_once():
    """The DMO and mg1 restarted in the same hour (before protocol 4 the resumed DMO refused mg1's new
    registration as a duplicate, and mg1 was billed every later hour as missing), with mg1's new registration
    lost once, and then both again across midnight."""
    hour_2, midnight = STEPS.index((1, "realtime", 2)), STEPS.index((2, "bidding", None))
    with tempfile.TemporaryDirectory() as tmp:
        out = run({hour_2: [("mg1", 1), ("dmo", 1)], midnight: [("dmo", 0), ("mg1", 0)]}, [False] * 2 + [True],
                  False, Path(tmp) / "journal.jsonl")
    assert out["settled"][2]["mg1"] == {h - 1: (metered("mg1", 2, h),) for h in range(1, HOURS + 1)}
    assert out["refused"]["mg1"] == []


def test_an_agent_restarted_after_reporting_its_hour_goes_on_at_the_next_without_a_refusal():
    """mg1 reports hour 2 and restarts while the DMO still waits for mg2: it rejoins without that hour's grid
    state, so it does not report the hour twice (a second report would be refused)."""
    hour_2 = STEPS.index((1, "realtime", 2))
    with tempfile.TemporaryDirectory() as tmp:
        out = run({hour_2: [("mg1", 1)]}, [], False, Path(tmp) / "journal.jsonl",
                  frozenset({(hour_2, 0, "mg2"), (hour_2, 1, "mg2"), (hour_2, 2, "mg2")}))
    assert out["refused"] == {"mg1": [], "mg2": []}
    assert out["settled"][1]["mg1"][1] == (metered("mg1", 1, 2),)
