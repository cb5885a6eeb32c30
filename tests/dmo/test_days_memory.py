"""What the DMO keeps in memory does not grow with the days of a run (dmo/operator/finished.py): a settled day's
bids, schedules, statements and the agents' realised days leave memory once the day is settled, and the run's
result still gives every day.

The DMO runs its real days in this process on a loopback bus that stands for Zenoh and two scripted agents: each
message the DMO publishes is answered at once on its event queue, so no deadline is waited out and no thread runs.
What is counted is the message and statement objects alive in the process as each day's last hour starts.
"""

from __future__ import annotations

import gc
import itertools

from dmo.market.settlement import Statement
from dmo.operator.config import DayConfig
from dmo.operator.day import MarketDay
from dmo.operator.events import Left, Received
from messages import Bid, MeterReport, Registration, Schedule, decode, encode
from messages.keys import Keys
from messages.schemas import AgentDay, Envelope, MessageCounts
from scenarios.horizon import HOURS

DAYS = 3
AGENTS = ("mg1", "mg2")
K = 2
AWARD = 1.0


class LoopbackAgents:
    """A bus for the DMO whose agents answer what it publishes: they register, bid nothing, schedule their award,
    meter it hour by hour and report each realised day after its last meter report."""

    def __init__(self, run_id: str):
        self.keys, self.run_token = Keys(run_id), ""
        self.on_reject = self.tap = None
        self.events = None  # the DMO's event queue
        self.seq = itertools.count()
        self.awards: dict[str, tuple[float, ...]] = {}

    def subscribe(self, *args, **kwargs):
        pass

    def present(self, timeout_s: float = 1.0) -> set[str]:
        return set(AGENTS)  # each scripted agent is there until it leaves (a "leave" event)

    def watch_presence(self, *args, **kwargs):
        pass

    def serve(self, *args, **kwargs):
        pass

    def publish(self, msg):
        for answer in self._answers(msg):
            stamped = answer.model_copy(update={"run": self.run_token, "incarnation": 1, "seq": next(self.seq)})
            payload = encode(stamped)
            self.events.put(Received(self.keys.for_message(stamped), decode(payload), payload))
        return msg

    def _answers(self, msg):
        day = msg.market_day
        if msg.kind == "clock" and msg.phase == "registration":
            return [Registration(sender=a, market_day=day, case="scripted", max_import_mw=10.0, max_export_mw=10.0)
                    for a in AGENTS]
        if msg.kind == "call_for_bids":
            return [Bid(sender=a, market_day=day, hours=((),) * HOURS) for a in AGENTS]
        if msg.kind == "award":
            self.awards[msg.agent] = msg.p_sch_mw
            return [Schedule(sender=msg.agent, market_day=day, status="scripted", commitment={}, expected_cost=0.0,
                             p_m_expected_mw=msg.p_sch_mw, scenarios=1, mip_gap=0.0)]
        if msg.kind == "grid_state":
            out = []
            for a in AGENTS:
                p_m = tuple(self.awards[a][msg.hour - 1] if up else 0.0 for up in msg.connected)
                out.append(MeterReport(sender=a, market_day=day, hour=msg.hour, subperiods=msg.subperiods, p_m_mw=p_m,
                                       deviation_mw=tuple(x - self.awards[a][msg.hour - 1] for x in p_m)))
                if msg.hour == HOURS:
                    out.append(realised_day(a, day))
            return out
        return []


def realised_day(agent: str, market_day: str) -> AgentDay:
    return AgentDay(sender=agent, market_day=market_day, generation=100.0, startup=10.0, curtailment=0.0,
                    penalty=5.0, total=115.0, curtailment_mwh=0.0, deviation_mwh=0.0, units={}, stored_mwh=None,
                    compute=(), messages=MessageCounts(published=1, received=1, rejected={}, handler_errors=0,
                                                       ignored={}, sent_again=0, asked=0, faults_injected={}))


def alive() -> int:
    """Messages and statements alive in this process."""
    gc.collect()
    return sum(1 for o in gc.get_objects() if isinstance(o, (Envelope, Statement)))


def test_the_dmo_holds_no_more_messages_on_its_last_day_than_on_its_first_and_still_reports_every_day():
    config = DayConfig(market_day="2026-07-01", agents=len(AGENTS), iso_price=(50.0,) * HOURS, import_limit=100.0,
                       export_limit=100.0, penalty=150.0, credit=0.0, subperiods=K, islanded_hours=(7,),
                       fixed_awards=(AWARD,) * HOURS, registration_s=30.0, bids_s=30.0, schedule_s=30.0,
                       hour_s=30.0, linger_s=0.0, days=DAYS)
    bus = LoopbackAgents("flat1")
    counted: dict[int, int] = {}
    market = None

    def progress(phase, hour):
        if phase == "realtime" and hour == HOURS:  # as dmosim run samples each role's memory
            counted[market.state.day] = alive()

    market = MarketDay(bus, config, progress)
    bus.events = market.events
    result = market.run()
    assert sorted(counted) == list(range(1, DAYS + 1))
    # what the days before would keep: 8 more a day (2 bids, schedules, statements and realised days)
    assert counted[DAYS] == counted[1], counted
    report = result.report("flat1", {})
    assert [d.day for d in report.days] == list(range(1, DAYS + 1)) and report.incidents == []
    assert report.accepted_messages["meter_report"] == DAYS * HOURS * len(AGENTS)
    assert {a: [(d.day, d.total) for d in days] for a, days in report.realised.items()} == {
        a: [(d, 115.0) for d in range(1, DAYS + 1)] for a in AGENTS}
    assert result.last.state.day == DAYS and set(result.last.statements) == set(AGENTS)


LAST_DAY = "2026-07-02"  # of a two-day run


class LateReporters(LoopbackAgents):
    """Agents that report their realised day once they have the day's summary, and then leave: on the last day that
    is while the DMO lingers for them."""

    def _answers(self, msg):
        if msg.kind == "day_summary":
            return [realised_day(a, msg.market_day) for a in AGENTS]
        out = super()._answers(msg)
        return [m for m in out if m.kind != "agent_day"]

    def publish(self, msg):
        super().publish(msg)
        if msg.kind == "day_summary" and msg.market_day == LAST_DAY:
            for a in AGENTS:
                self.events.put(Left(a))
        return msg


def test_realised_days_reported_while_the_dmo_lingers_are_counted_in_the_last_days_report():
    config = DayConfig(market_day="2026-07-01", agents=len(AGENTS), iso_price=(50.0,) * HOURS, import_limit=100.0,
                       export_limit=100.0, penalty=150.0, credit=0.0, subperiods=K, islanded_hours=(),
                       fixed_awards=(AWARD,) * HOURS, registration_s=30.0, bids_s=30.0, schedule_s=30.0,
                       hour_s=30.0, linger_s=30.0, days=2)
    bus = LateReporters("late1")
    market = MarketDay(bus, config, lambda phase, hour: None)
    bus.events = market.events
    report = market.run().report("late1", {})
    assert report.market_days == ["2026-07-01", LAST_DAY]
    assert [d.accepted_messages.get("agent_day", 0) for d in report.days] == [0, 2 * len(AGENTS)]
    assert {a: [d.market_day for d in days] for a, days in report.realised.items()} == {
        a: ["2026-07-01", LAST_DAY] for a in AGENTS}
