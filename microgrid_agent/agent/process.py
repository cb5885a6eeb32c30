"""A microgrid agent's process: its decisions (machine.py, ``AgentMachine``) driven over a Bus.

Zenoh's callback threads only enqueue what arrives; the agent hands it to its machine in order on its main thread, and
carries out what the machine says: it solves the schedule there and then, so a long solve delays, but never reorders
or drops, what comes next; it publishes what it sends, waits for receipts and asks the DMO for a statement that did
not come. The run ends when the machine is done with the last day the DMO's clock announces, or when the agent hears
nothing for ``idle_s``.

Nothing is waited out for want of one message (docs/protocol.md, "Receipts and sending again"): what the agent
sends goes again until the DMO's receipt comes (delivery.py), and when the DMO has been silent for a while the
agent asks it for the latest of what it is waiting for (its clock, then what the machine waits for: the call for
bids, the award, the grid state, the statement and summary). A refusal in a receipt goes to the machine, and a
refused registration ends the agent with the DMO's reason (exit 1).

Each message of the DMO's is timed here as the agent handled it (wall and CPU time, the schedule's solve of an award
included, and the wait for its turn among the agents of a host, slots.py), and the machine reports the times in the
day's ``agent_day``.
"""

from __future__ import annotations

import logging
import queue
import time

from messages import DaySummary, MessageError, Receipt, check_route, decode
from messages.keys import parse_key
from messages.schemas import HandlingTime, MessageCounts
from messages.transport import Bus
from messages.transport.heap import return_free_memory
from scenarios.case import Case

from .delivery import Delivery, Joining, RefusedPayload, Silence
from .machine import (Action, AgentConfig, AgentMachine, AskStatement, AwaitReceipts, Handled, NoStatement, Send, Solve,
                      Solved)
from .slots import computing
from .strategies import ChosenStrategy

log = logging.getLogger("dmosim.agent")


class AgentTimeout(RuntimeError):
    pass


class MicrogridAgent:
    """One microgrid's agent over ``bus``: its ``AgentMachine`` (made of the other arguments) driven by what the DMO
    sends."""

    def __init__(self, bus: Bus, case: Case, config: AgentConfig, market_day: str,
                 strategy: ChosenStrategy | None = None):
        self.bus, self.config = bus, config
        self.machine = AgentMachine(bus.name, case, config, market_day, strategy)
        self.events: queue.Queue = queue.Queue()
        self.delivery = Delivery(bus.republish)
        self.asked = 0  # messages the agent asked the DMO for (it had heard nothing for a while) and handled
        k = bus.keys
        # What the agent hears from the DMO, by kind: where it listens, and what it asks for.
        self._dmo_keys = {"clock": k.clock(), "call_for_bids": k.call_for_bids(), "award": k.award(self.id),
                          "grid_state": k.grid(), "settlement_statement": k.statement(self.id),
                          "day_summary": k.summary()}

    @property
    def id(self) -> str:
        return self.bus.name

    def run(self) -> DaySummary:
        try:
            return self._run()
        finally:
            self.delivery.close()

    def _run(self) -> DaySummary:
        k = self.bus.keys
        put = lambda key, msg, t: self.events.put(msg)  # noqa: E731
        for key in self._dmo_keys.values():
            self.bus.subscribe(key, put)
        self.bus.subscribe(k.receipt(self.id), self._receipt_arrived)
        self._join_where_the_run_is()  # the DMO has answered: it listens (docs/protocol.md, step 3)
        self.bus.wait_for_subscribers(k.register(self.id), self.config.idle_s)  # and this client knows it does
        self._publish(self.machine.registration())
        # Nothing else goes before the registration's receipt: a restarted process's bid, schedule or report would
        # be refused as unregistered (and not sent again) were it to overtake a lost registration.
        if not self.delivery.drained(self.config.idle_s):
            raise AgentTimeout(f"{self.id}: no receipt for my registration in {self.config.idle_s:g} s")
        log.info("%s registered", self.id)
        while not self.machine.done:
            self._take(self._next_message())
        # The DMO lingers after the last summary (on the logical clock, until this agent leaves): what is still
        # unreceipted (the last agent_day) has that long.
        if not self.delivery.drained(LEAVING_S):
            log.warning("%s: leaving with %d payload(s) not receipted", self.id, self.delivery.waiting())
        return self.machine.summary

    def _take(self, event) -> None:
        """Hand ``event`` to the machine and carry out what it says. A message of the DMO's is timed, and its time
        handed to the machine after it (``Handled``), with the message counts by then."""
        if isinstance(event, RefusedPayload):  # no computation to account for
            self._carry_out(self._decide(event))
            return
        started_at = time.time_ns()
        # CPU of this thread: agents sharing a process each count their own (the process's counted, in each agent
        # that waited for its turn, what the others computed meanwhile)
        started = (time.perf_counter(), time.thread_time())
        with computing():  # a turn among the agents of a host (slots.py): waiting counts in wall_s and turn_s
            turn_s = time.perf_counter() - started[0]
            actions = self._decide(event)
            ended = (time.perf_counter(), time.thread_time())
        self._carry_out(actions)
        handled = HandlingTime(kind=event.kind, hour=getattr(event, "hour", None), wall_s=ended[0] - started[0],
                               cpu_s=ended[1] - started[1], started_at=started_at, turn_s=turn_s)
        self._carry_out(self._decide(Handled(handled, self.message_counts())))

    def _decide(self, event) -> list[Action]:
        """What the machine does about ``event``. A solve it asks for runs here and now, on this thread, and its
        result goes in at once (``Solved``): the solve is part of the handling, as it was when the machine called it."""
        actions = self.machine.handle(event)
        if actions and isinstance(actions[-1], Solve):
            return actions[:-1] + self._decide(Solved(actions[-1].job.run()))
        return actions

    def _carry_out(self, actions: list[Action]) -> None:
        """Do what the machine said, in order. Once a schedule has gone the day's solves are over, and once an
        agent_day has gone its hours: what their models took from the C heap goes back."""
        for action in actions:
            if isinstance(action, Send):
                self._publish(action.msg)
            elif isinstance(action, AwaitReceipts):
                self._await_receipts()
            elif isinstance(action, AskStatement):
                self._await_statement()
        if any(isinstance(a, Send) and a.msg.kind in ("schedule", "agent_day") for a in actions):
            return_free_memory()

    def _await_receipts(self) -> None:
        """Before the agent_day: wait for the receipts of everything sent, at most ``receipts_s``."""
        if not self.delivery.drained(wait := self.config.waits(self.config.receipts_s)):
            log.warning("%s: my last meter report has no receipt after %g s; sending my realised day anyway", self.id,
                        wait)

    def _next_message(self):
        """The next message from the DMO. When it has been silent for a while, ask it for the latest of what this
        agent waits for (a message of it may have been lost), then again at doubling intervals; give up after
        ``idle_s`` of silence."""
        silence = Silence(self.config.idle_s, time.monotonic(), ASK_AFTER_S, ASK_AT_MOST_S)
        wait = silence.wait
        while True:
            try:
                return self.events.get(timeout=wait)
            except queue.Empty:
                pass
            if silence.over(time.monotonic()):
                raise AgentTimeout(f"{self.id}: nothing from the DMO for {self.config.idle_s:g} s")
            self._ask_the_dmo()
            wait = silence.asked(time.monotonic())

    def _ask_the_dmo(self) -> None:
        """Ask the DMO (docs/protocol.md, "Asking the DMO") for its clock, then for the latest message of each kind
        the machine waits for, and handle the answers that tell it something new as if they had come."""
        answers = self._latest([self._dmo_keys["clock"]])
        registering = any(m.kind == "clock" and m.phase == "registration" for m in answers)
        kinds = self.machine.waiting_for(registering)
        for msg in answers + self._latest([self._dmo_keys[kind] for kind in kinds]):
            if self.machine.wants(msg):
                self.asked += 1
                self.events.put(msg)

    def _latest(self, keys: list[str], timeout_s: float | None = None) -> list:
        """The DMO's latest valid message of this run on each of ``keys`` (none where it answers nothing), each
        answer waited for ``timeout_s`` (``ANSWER_S`` unless given)."""
        out = []
        for key in keys:
            for found, payload, _ in self.bus.fetch(key, timeout_s=timeout_s or ANSWER_S):
                try:
                    msg = decode(payload, expected_kind=parse_key(found).kind)
                    check_route(found, msg, self.bus.keys.run_id)
                except MessageError as err:
                    log.warning("%s: the DMO's answer on %s is refused: %s", self.id, found, err)
                    continue
                if msg.run == self.bus.run_token or not self.bus.run_token:
                    out.append(msg)
        return out

    def _join_where_the_run_is(self) -> None:
        """Ask the DMO for its clock (docs/protocol.md, "Asking the DMO") until it answers, as ``Joining`` says, at
        most ``idle_s``: its answer gives the run's token, which every message carries, and where the run is."""
        joining = Joining(self.config.idle_s, time.monotonic(), ANSWER_S, ASK_AT_MOST_S, ASK_AFTER_S / 4)
        while True:
            asked = time.monotonic()
            if clocks := self._latest([self._dmo_keys["clock"]], joining.wait):
                break
            pause = joining.unanswered(asked, time.monotonic())
            if pause is None:
                raise AgentTimeout(f"{self.id}: the DMO did not answer for {self.config.idle_s:g} s")
            time.sleep(pause)
        self.bus.run_token = clocks[0].run
        self.machine.join(clocks[0])

    def _await_statement(self) -> None:
        """The summary came before the agent's own statement: ask the DMO for it, then handle what comes for up to
        ``statement_s`` until the machine has it (and has ended the day); if it never came, say so and tell the
        machine."""
        wait = self.config.waits(self.config.statement_s)
        for msg in self._latest([self._dmo_keys["settlement_statement"]], min(5.0, wait)):
            self.events.put(msg)
        deadline = time.monotonic() + wait
        while self._awaiting_statement() and (left := deadline - time.monotonic()) > 0:  # receipts may still come
            try:
                self._take(self.events.get(timeout=left))
            except queue.Empty:
                break
        if self._awaiting_statement():
            log.warning("%s: gave up waiting for my settlement statement %g s after the day summary", self.id,
                        wait)
            self._carry_out(self._decide(NoStatement()))

    def _awaiting_statement(self) -> bool:
        """Whether the day still waits for its statement: once it came the machine ends the day (the next has no
        summary yet, or the run is done)."""
        return self.machine.summary is not None and not self.machine.done

    def message_counts(self) -> MessageCounts:
        """What the agent's process published, received and refused (transport), sent again, asked for and injected
        as faults, since it started. What it handled as no-ops (``ignored``) the machine fills in."""
        faults = self.bus.faults_injected()
        stats = self.bus.stats()
        return MessageCounts(published=stats["published"], received=stats["received"], rejected=stats["rejected"],
                             handler_errors=stats["handler_errors"], ignored={}, sent_again=self.delivery.resent,
                             asked=self.asked, faults_injected=faults)

    def _publish(self, msg) -> None:
        """Publish, and send again until the DMO's receipt comes."""
        self.bus.publish(msg, before_put=self.delivery.sent)

    def _receipt_arrived(self, key: str, receipt: Receipt, received_at: int) -> None:
        """On Zenoh's thread: stop sending the payload again at once (the main thread may be solving), then let the
        main thread see a refusal."""
        if receipt.run != self.bus.run_token:
            return
        mine = self.delivery.receipt(receipt)
        if mine is not None and not receipt.accepted:
            self.events.put(RefusedPayload(receipt, *mine))


LEAVING_S = 5.0  # how long a leaving agent waits for the receipts of what it sent last (a DMO that left sends none)
ASK_AFTER_S = 1.0     # silence after which the agent asks the DMO for what it waits for ...
ASK_AT_MOST_S = 8.0   # ... then at doubling intervals up to this
ANSWER_S = 2.0        # how long the DMO's answer is waited for; joining, doubled up to ASK_AT_MOST_S while it is busy
