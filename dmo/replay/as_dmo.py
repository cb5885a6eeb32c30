"""The DMO's side of a recorded day, played to one live agent process and settled by the recorded rules
(``dmosim replay --as-dmo``).

It stands in for the recorded DMO step by step: the recorded clock, call for bids, the agent's recorded award and
each hour's recorded grid state, each step sent once the live agent has answered the one before (its
registration, bid, schedule, the hour's meter report) or the timeout has passed. The agent's answers are accepted
by the same rules as the live DMO's (market/acceptance.py), bound to the recorded run's token, each answered with
a receipt, and settled as the DMO settles (the award's penalty, credit and sub-periods, its registration's max
import for missing data); the new statement and a day summary are sent to it. Like the DMO, it answers queries
with the latest message it sent on each key (the agent asks for the clock before it registers).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import queue
import threading
import time

from messages import MeterReport, Registration, decode, encode, make_receipt, make_rejection, sha256
from messages.codec import MessageError
from messages.schemas import AgentDay
from messages.recording import Player, RecordedMessage, Recording
from messages.transport import Bus

from ..market import acceptance
from ..market.acceptance import Refusal
from ..market.choice import ChosenRule
from ..market.settlement import accepted_day
from ..operator.events import Received, Unreadable
from ..operator.history import DayHistory, asks_history
from ..operator.outbox import day_summary
from .resettle import RecordedDay, as_message, recorded_rule

log = logging.getLogger("dmosim.replay")


class AsDmo:
    """The DMO's side of a recorded day, driven by one live agent's answers."""

    def __init__(self, bus: Bus, day: RecordedDay, agent: str, steps: list[tuple], timeout_s: float,
                 rule: ChosenRule | None = None):
        self.bus, self.day, self.agent, self.steps, self.timeout_s = bus, day, agent, steps, timeout_s
        self.rule = rule  # the recorded rule, as the caller was allowed to load it (None: a built-in by its name)
        self.events: queue.Queue = queue.Queue()
        self.player = Player(bus, [])
        self.registration: Registration | None = None
        self.meter: dict[int, tuple[float, ...]] = {}
        self.answered: set[str] = set()
        self.realised: set[str] = set()  # the market day of the agent's realised day, once taken
        self.incidents: list[str] = []
        self.rejected = 0
        self.phase, self.hour = "registration", None
        self.grid: tuple[bool, ...] | None = None  # the hour's recorded grid state
        self.taken: set[str] = set()  # SHA-256 of each payload accepted: a copy of one is receipted again
        self.history = DayHistory()
        self.run_token = steps[0][0].run if steps else ""
        bus.run_token = self.run_token
        bus.tap = self.history.record
        bus.on_reject = lambda key, payload, err: self.events.put(Unreadable(key, payload, err))

    def run(self, stop: threading.Event) -> dict:
        self.bus.subscribe(self.bus.keys.agent_all(self.agent), lambda k, m, t, p: self.events.put(Received(k, m, p)),
                           payload=True)
        self.bus.serve(self.bus.keys.everything(), self.history.answer, slow=asks_history)
        with self.player:
            for clock, messages in self.steps:
                if stop.is_set():
                    raise KeyboardInterrupt
                self.phase, self.hour = clock.phase, clock.hour
                if clock.phase == "settlement":
                    break
                for m in messages:
                    self.player.publish(m)
                    self.history.record(self.player.key(m), m.payload, time.time_ns())
                    if m.kind == "grid_state":
                        self.grid = decode(m.payload).connected
                self._await_answer(stop)
                if clock.phase == "registration" and self.registration is None:
                    raise RuntimeError(f"agent {self.agent} did not register within {self.timeout_s:g} s")
        self.phase, self.hour = "settlement", None
        while not self.events.empty():  # what arrived after the last hour is late
            self._handle(self.events.get_nowait())
        return self._settle()

    def _expected(self) -> str | None:
        if self.phase == "realtime":
            return f"meter report for hour {self.hour}"
        return acceptance.DUE.get(self.phase)

    def _done(self) -> bool:
        if self.phase == "realtime":
            return (self.hour - 1) in self.meter
        expected = self._expected()
        return expected is None or expected in self.answered

    def _await_answer(self, stop: threading.Event) -> None:
        expected = self._expected()
        if expected is None:
            return
        deadline = time.monotonic() + self.timeout_s
        while not self._done():
            left = deadline - time.monotonic()
            if left <= 0 or stop.is_set():
                if stop.is_set():
                    raise KeyboardInterrupt
                self.incidents.append(f"{self._when()}: no {expected} from {self.agent} within {self.timeout_s:g} s")
                log.warning(self.incidents[-1])
                return
            try:
                event = self.events.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            self._handle(event)

    def _handle(self, event: Received | Unreadable) -> None:
        if isinstance(event, Unreadable):
            self._reject(event.key, event.payload, event.error)
            return
        key, msg, payload = event.key, event.msg, event.payload
        if sha256(payload) in self.taken:  # sent again for want of a receipt
            self.bus.publish(make_receipt(self.agent, payload, None, market_day=self.day.market_day))
            return
        refusal = self.refusal(msg)
        if refusal:
            code, reason = refusal
            return self._reject(key, payload, MessageError(reason, code))
        self.taken.add(sha256(payload))
        self.bus.publish(make_receipt(self.agent, payload, None, market_day=self.day.market_day))
        if isinstance(msg, Registration):
            self.registration = msg
            self.answered.add("registration")
        elif isinstance(msg, MeterReport):
            self.meter[msg.hour - 1] = msg.p_m_mw
        elif isinstance(msg, AgentDay):
            self.realised.add(msg.market_day)
        else:
            self.answered.add(msg.kind)

    def refusal(self, msg) -> Refusal | None:
        """The live DMO's rules (market/acceptance.py), for the one agent of this day."""
        refusal = acceptance.check_run(msg, self.run_token) or acceptance.check_day(msg, self.day.market_day)
        if refusal:
            return refusal
        if isinstance(msg, Registration) and self.registration is not None:
            return acceptance.repeated("registration", msg.sender)
        registered = {} if self.registration is None else {self.agent: self.registration}
        refusal = acceptance.check_registered(msg, registered)
        if refusal or isinstance(msg, Registration):
            return refusal
        if isinstance(msg, AgentDay):  # taken in the day's last hour and its settlement, as the DMO takes it
            return acceptance.check_agent_day(msg, self.day.market_day, self.day.market_day, self.phase, self.hour,
                                              self.realised)
        if self.phase == "realtime" and isinstance(msg, MeterReport):
            return acceptance.check_meter_report(msg, self.hour, self.day.terms.subperiods, self.meter,
                                                 self.registration, self.grid)
        if msg.kind == acceptance.DUE.get(self.phase):
            return acceptance.repeated(msg.kind, msg.sender) if msg.kind in self.answered else None
        return acceptance.out_of_phase(msg, self.phase)

    def _when(self) -> str:
        return f"{self.phase}{f' hour {self.hour}' if self.hour else ''}"

    def _reject(self, key: str, payload: bytes, err: MessageError) -> None:
        self.rejected += 1
        self.incidents.append(f"{self._when()}: rejected message on {key.split('/', 2)[-1]}: {err.reason}")
        log.warning(self.incidents[-1])
        self.bus.publish(make_rejection(key, payload, err, market_day=self.day.market_day, offender=self.agent))
        self.bus.publish(make_receipt(self.agent, payload, err, market_day=self.day.market_day))

    def _settle(self) -> dict:
        day, terms, agent = self.day, self.day.terms, self.agent
        prices, own = day.prices([agent])
        statements, _ = (self.rule or recorded_rule(day)).settle(accepted_day(
            {agent: day.awards[agent].p_sch_mw}, prices, {agent: self.meter},
            subperiods=terms.subperiods, registered={agent: self.registration}, agent_prices=own))
        message = as_message(day, statements[agent])
        self.bus.publish(message)
        self.bus.publish(day_summary(day.market_day, (agent,), prices, statements, self.rejected, ()))
        recorded = day.statements.get(agent)
        return {"run_id": self.bus.keys.run_id, "market_day": day.market_day, "agent": agent,
                "statement": json.loads(message.model_dump_json(exclude={"seq", "sent_at"})),
                "recorded_total": recorded.total if recorded else None,
                "difference": round(message.total - recorded.total, 2) if recorded else None,
                "meter_reports": len(self.meter), "rejected_messages": self.rejected, "incidents": self.incidents}


def dmo_steps(rec: Recording, agent: str, market_day: str) -> list[tuple]:
    """The recorded DMO messages of ``market_day`` the agent would see, grouped by the clock message that opens
    each step: [(Clock, [RecordedMessage...])], the clock itself first in each list.

    The day is played as a run of one day: its clocks say day 1 of 1, and a day after the first of its run, which
    has no registration phase of its own, opens with one."""
    steps: list[tuple] = []
    for m in rec.in_log_order():
        if m.invalid or not m.relative_key.startswith("dmo/"):
            continue
        if m.kind == "clock":
            try:
                clock = decode(m.payload, expected_kind="clock")
            except MessageError:
                continue
            if clock.market_day == market_day:
                steps.append(_one_day(clock, m))
        elif steps and (m.kind in ("call_for_bids", "grid_state") or m.relative_key == f"dmo/award/{agent}"):
            steps[-1][1].append(m)
    if steps and steps[0][0].phase != "registration":
        clock, m = steps[0][0], steps[0][1][0]
        steps.insert(0, _one_day(clock.model_copy(update={"phase": "registration", "hour": None}), m))
    return steps


def _one_day(clock, m: RecordedMessage) -> tuple:
    """A step opened by ``clock`` as a run of one day says it: day 1 of 1; ``m`` re-encoded unless it says so."""
    one = clock.model_copy(update={"day": 1, "days": 1})
    return one, [m if one == decode(m.payload) else dataclasses.replace(m, payload=encode(one))]


def render(result: dict) -> str:
    st = result["statement"]
    rows = [f"agent {result['agent']} against the recorded DMO of {result['market_day']} (run {result['run_id']})",
            f"{'hour':>4}{'award MW':>10}{'import MWh':>12}{'dev. MWh':>10}{'energy $':>11}{'penalty $':>11}{'total $':>11}"]
    for line in st["lines"]:
        rows.append(f"{line['hour']:>4}{line['p_sch_mw']:>10.3f}{line['import_mwh']:>12.3f}{line['deviation_mwh']:>10.3f}"
                    f"{line['energy_charge']:>11,.2f}{line['deviation_penalty']:>11,.2f}{line['total']:>11,.2f}"
                    + ("  missing" if line["missing"] else ""))
    rows.append(f"total: ${st['total']:,.2f} (energy ${st['energy_charge']:,.2f}, penalty ${st['deviation_penalty']:,.2f}, "
                f"credit ${st['deviation_credit']:,.2f}); {result['meter_reports']}/24 meter reports")
    if result["recorded_total"] is not None:
        rows.append(f"recorded agent's total: ${result['recorded_total']:,.2f}; difference ${result['difference']:+,.2f}")
    for incident in result["incidents"]:
        rows.append(f"incident: {incident}")
    if result.get("recording"):
        rows.append(f"recording: {result['recording']}")
    return "\n".join(rows)
