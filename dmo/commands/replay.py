"""``dmosim replay PATH``: republish a recorded day over Zenoh, or, with ``--as-dmo``, play the DMO's side of it to
a live agent process and settle that agent by the recorded rules.

Plain replay publishes every selected message at its recorded spacing scaled by ``--rate``, under a new run
prefix (``--run-id``, default a new id), so it never mixes with a live run.

``--as-dmo`` stands in for the recorded DMO, step by step: the recorded clock, call for bids, the agent's recorded
award and each hour's recorded grid state, each step sent once the live agent has answered the one before (its
registration, bid, schedule, the hour's meter report) or ``--timeout`` has passed. The live agent schedules
against the recorded award and grid, its reports are checked and settled as the DMO does (the award's penalty,
credit and sub-periods, its registration's max import for missing data), and the new statement and a day
summary are sent to it. With ``--record PATH`` the replayed day, the agent's messages included, is recorded.
"""

from __future__ import annotations

import json
import logging
import queue
import signal
import sys
import threading
import time

from messages import DMO, Bid, DaySummary, MeterReport, Registration, Schedule, decode, make_rejection
from messages.codec import MessageError
from messages.keys import check_agent_id, check_run_id, new_run_id
from messages.recording import Recorder, RecordingWriter
from messages.replay import Player, select
from messages.schemas import AgentTotals
from messages.transport import Bus

from ..console import UsageError, print_json, progress
from ..resettle import RecordedDay, ResettleError, as_message, recorded_day
from ..settlement import settle
from .info import load
from .record import check_output
from .roles import _bus_config, setup_logging

log = logging.getLogger("dmosim.replay")


def run(args) -> int:
    setup_logging("replay", args.quiet)
    run_id = args.run_id or new_run_id()
    try:
        check_run_id(run_id)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if not args.as_dmo and (args.agent or args.record):
        raise UsageError("--agent and --record go with --as-dmo")
    rec = load(args.path)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    if args.as_dmo:
        return AsDmo.run_command(args, rec, run_id, stop)

    messages = select(rec, args.topics, args.start_offset)
    if not messages:
        raise UsageError(f"{args.path}: nothing to replay" + (f" on keys matching {', '.join(args.topics)}"
                                                              if args.topics else "")
                         + (f" after {args.start_offset:g} s" if args.start_offset else ""))
    if rec.cut_note:
        print(f"warning: {args.path}: {rec.cut_note}; replaying what was recorded before the cut", file=sys.stderr)
    with Bus(run_id, "replay", _bus_config(args, "peer"), announce=False) as bus, Player(bus, messages) as player:
        rate = "as fast as possible" if not args.rate else f"{args.rate:g}x"
        _say(args, f"replaying {len(messages)} messages of {args.path} under {bus.keys.prefix}/ at {rate}"
                   + (", looping (Ctrl-C stops)" if args.loop else ""))
        if args.wait_for_subscriber and not player.wait_for_subscriber(args.wait_for_subscriber):
            _say(args, f"nobody listens after {args.wait_for_subscriber:g} s; replaying anyway")
        stats = player.play(args.rate, stop, loop=args.loop)
        player.drain()
    result = {"run_id": run_id, "key_prefix": f"dmosim/{run_id}", "selected": len(messages),
              "published": stats.published, "loops": stats.loops, "seconds": round(stats.seconds, 3),
              "msgs_per_s": round(stats.published / stats.seconds) if stats.seconds > 0 else None,
              "interrupted": stop.is_set()}
    if args.json:
        print_json(result)
    else:
        print(f"replayed {stats.published} messages under {result['key_prefix']}/ in {stats.seconds:.2f} s"
              + (f" ({stats.loops} loops)" if args.loop else "") + (" (interrupted)" if stop.is_set() else ""))
    return 0


def _say(args, text: str) -> None:
    if not args.quiet:
        progress(text)


class AsDmo:
    """The DMO's side of a recorded day, driven by one live agent's answers."""

    def __init__(self, bus: Bus, day: RecordedDay, agent: str, steps: list[tuple], timeout_s: float):
        self.bus, self.day, self.agent, self.steps, self.timeout_s = bus, day, agent, steps, timeout_s
        self.events: queue.Queue = queue.Queue()
        self.player = Player(bus, [])
        self.registration: Registration | None = None
        self.meter: dict[int, tuple[float, ...]] = {}
        self.answered: set[str] = set()
        self.incidents: list[str] = []
        self.rejected = 0
        self.phase, self.hour = "registration", None
        bus.on_reject = lambda key, payload, err: self.events.put(("reject", key, payload, err))

    @classmethod
    def run_command(cls, args, rec, run_id: str, stop: threading.Event) -> int:
        try:
            day = recorded_day(rec)
        except ResettleError as exc:
            raise UsageError(str(exc)) from None
        agent = args.agent or sorted(day.awards)[0]
        try:
            check_agent_id(agent)
        except ValueError as exc:
            raise UsageError(str(exc)) from None
        if agent not in day.awards:
            raise UsageError(f"{args.path}: no award recorded for {agent} (awarded: {', '.join(sorted(day.awards))})")
        out = check_output(args.record, args.overwrite) if args.record else None
        steps = dmo_steps(rec, agent)
        if rec.cut_note:
            print(f"warning: {args.path}: {rec.cut_note}; playing what was recorded before the cut", file=sys.stderr)
        config = _bus_config(args, "router")
        endpoint = (config.listen or config.connect or ("zenoh's default",))[0]
        _say(args, f"playing the DMO of {args.path} ({day.market_day}) under dmosim/{run_id}/ for agent {agent}; start "
                   f"it with: dmosim agent --id {agent} --run-id {run_id} --market-day {day.market_day} --connect "
                   f"{endpoint}")
        writer = RecordingWriter(out, run_id) if out else None
        recorder_stop, recorder_thread = threading.Event(), None
        try:
            with Bus(run_id, DMO, config) as bus:
                if writer is not None:
                    meta = {k: v for k, v in rec.metadata.items() if k in ("config", "seed")}
                    writer.start({**meta, "command": "dmosim replay --as-dmo", "source": str(args.path),
                                  "source_run_id": rec.run_id, "market_day": day.market_day, "agents": agent},
                                 [(a.name, a.media_type, a.data) for a in rec.attachments])
                    recorder = Recorder(bus, writer, announce=False)
                    recorder.start()
                    recorder_thread = threading.Thread(target=recorder.run, args=(recorder_stop,), name="recorder")
                    recorder_thread.start()
                driver = cls(bus, day, agent, steps, args.timeout)
                result = driver.run(stop)
                time.sleep(0.2)  # the last messages reach the recorder
        finally:
            recorder_stop.set()
            if recorder_thread is not None:
                recorder_thread.join()
            elif writer is not None:
                writer.close()
        result["recording"] = str(out.resolve()) if out else None
        if args.json:
            print_json(result)
        else:
            print(render(result))
        return 0

    # --- the day ---------------------------------------------------------------------------------------------

    def run(self, stop: threading.Event) -> dict:
        self.bus.subscribe(self.bus.keys.agent_all(self.agent), lambda k, m, t: self.events.put(("msg", k, m)))
        with self.player:
            for clock, messages in self.steps:
                if stop.is_set():
                    raise KeyboardInterrupt
                self.phase, self.hour = clock.phase, clock.hour
                if clock.phase == "settlement":
                    break
                for m in messages:
                    self.player.publish(m)
                self._await_answer(stop)
                if clock.phase == "registration" and self.registration is None:
                    raise RuntimeError(f"agent {self.agent} did not register within {self.timeout_s:g} s")
        self.phase, self.hour = "settlement", None
        while not self.events.empty():  # what arrived after the last hour is late
            self._handle(self.events.get_nowait())
        return self._settle()

    def _expected(self) -> tuple[type, str] | None:
        if self.phase == "registration":
            return Registration, "registration"
        if self.phase == "bidding":
            return Bid, "bid"
        if self.phase == "scheduling":
            return Schedule, "schedule"
        if self.phase == "realtime":
            return MeterReport, f"meter report for hour {self.hour}"
        return None

    def _done(self) -> bool:
        if self.phase == "realtime":
            return (self.hour - 1) in self.meter
        expected = self._expected()
        return expected is None or expected[1] in self.answered

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
                self.incidents.append(f"{self.phase}{f' hour {self.hour}' if self.hour else ''}: no {expected[1]} "
                                      f"from {self.agent} within {self.timeout_s:g} s")
                log.warning(self.incidents[-1])
                return
            try:
                event = self.events.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            self._handle(event)

    def _handle(self, event) -> None:
        if event[0] == "reject":
            _, key, payload, err = event
            self._reject(key, payload, err)
            return
        _, key, msg = event
        terms = self.day.terms
        if msg.market_day != self.day.market_day:
            return self._refuse(key, msg, "wrong_day", f"market day {msg.market_day}, expected {self.day.market_day}")
        if isinstance(msg, Registration):
            if self.registration is not None:
                return self._refuse(key, msg, "duplicate", f"{msg.sender} is already registered")
            self.registration = msg
            self.answered.add("registration")
            return None
        if self.registration is None:
            return self._refuse(key, msg, "unregistered", f"{msg.sender} is not registered")
        expected = self._expected()
        if isinstance(msg, MeterReport) and self.phase == "realtime":
            if msg.subperiods != terms.subperiods:
                return self._refuse(key, msg, "invalid", f"{msg.subperiods} sub-periods, the day has {terms.subperiods}")
            if msg.hour != self.hour:
                return self._refuse(key, msg, "late" if msg.hour < self.hour else "invalid",
                                    f"meter report for hour {msg.hour} during hour {self.hour}")
            if (msg.hour - 1) in self.meter:
                return self._refuse(key, msg, "duplicate", f"second meter report for hour {msg.hour}")
            if max(msg.p_m_mw) > self.registration.max_import_mw + 1e-9:
                return self._refuse(key, msg, "invalid", f"P_M {max(msg.p_m_mw)} MW above registered max "
                                                         f"{self.registration.max_import_mw}")
            self.meter[msg.hour - 1] = msg.p_m_mw
            return None
        if expected is not None and isinstance(msg, expected[0]) and expected[1] not in self.answered:
            self.answered.add(expected[1])
            return None
        return self._refuse(key, msg, "late" if self.phase in ("realtime", "settlement") else "invalid",
                            f"{msg.kind} is out of phase (now {self.phase})")

    def _refuse(self, key: str, msg, code: str, reason: str) -> None:
        from messages import encode  # noqa: PLC0415

        self._reject(key, encode(msg), MessageError(reason, code))

    def _reject(self, key: str, payload: bytes, err: MessageError) -> None:
        self.rejected += 1
        self.incidents.append(f"{self.phase}{f' hour {self.hour}' if self.hour else ''}: rejected message on "
                              f"{key.split('/', 2)[-1]}: {err.reason}")
        log.warning(self.incidents[-1])
        self.bus.publish(make_rejection(key, payload, err, market_day=self.day.market_day, offender=self.agent))

    def _settle(self) -> dict:
        day, terms, agent = self.day, self.day.terms, self.agent
        cap = self.registration.max_import_mw
        statements, _ = settle({agent: day.awards[agent].p_sch_mw}, terms.clearing_price_per_mwh, {agent: self.meter},
                               subperiods=terms.subperiods, penalty=terms.penalty_per_mwh, credit=terms.credit_per_mwh,
                               p_m_max={agent: cap})
        message = as_message(day, statements[agent])
        self.bus.publish(message)
        self.bus.publish(DaySummary(
            sender=DMO, market_day=day.market_day, agents=(agent,), clearing_price_per_mwh=terms.clearing_price_per_mwh,
            totals={agent: AgentTotals(energy_charge=message.energy_charge, deviation_penalty=message.deviation_penalty,
                                       deviation_credit=message.deviation_credit, total=message.total)},
            rejected_messages=self.rejected, incidents=()))
        recorded = day.statements.get(agent)
        return {"run_id": self.bus.keys.run_id, "market_day": day.market_day, "agent": agent,
                "statement": json.loads(message.model_dump_json(exclude={"seq", "sent_at"})),
                "recorded_total": recorded.total if recorded else None,
                "difference": round(message.total - recorded.total, 2) if recorded else None,
                "meter_reports": len(self.meter), "rejected_messages": self.rejected, "incidents": self.incidents}


def dmo_steps(rec, agent: str) -> list[tuple]:
    """The recorded DMO messages the agent would see, grouped by the clock message that opens each step:
    [(Clock, [RecordedMessage...])], the clock itself first in each list."""
    steps: list[tuple] = []
    for m in rec.in_log_order():
        if m.invalid or not m.relative_key.startswith("dmo/"):
            continue
        if m.kind == "clock":
            try:
                steps.append((decode(m.payload, expected_kind="clock"), [m]))
            except MessageError:
                continue
        elif steps and (m.kind in ("call_for_bids", "grid_state") or m.relative_key == f"dmo/award/{agent}"):
            steps[-1][1].append(m)
    return steps


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
