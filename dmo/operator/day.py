"""The DMO's market days over a Bus and the wall clock: the Zenoh driver of the DMO's machine (machine.py), which
decides everything (docs/architecture.md, "Machines and drivers").

The DMO reads everything it receives from one queue on its main thread and hands it to the machine in order, so
the day's state is touched by one thread only; Zenoh's callback threads just enqueue. The driver does what the
machine asks: it publishes (stamped by the bus), journals, tells who is present, keeps each agent's budget (the
bus's gate drops a sender over it unread, on Zenoh's threads), waits for events up to the deadline the machine
gives and says who it still waits for while it does. It keeps the day's traffic for late joiners (history.py), the
settled days and realised days on disk (finished.py), and before it leaves waits for a recorder to have asked for
the run's last messages.
"""

from __future__ import annotations

import logging
import math
import queue
import secrets
import time
from typing import Callable

from messages import Clock
from messages.budget import SenderBudget
from messages.keys import agent_of
from messages.transport import Bus
from messages.transport.heap import return_free_memory
from scenarios.names import RECORDER

from .actions import CheckPresence, Journaled, OpenWindow, Publish, Realised, Settled, Stop, Wait
from .config import DayConfig
from .events import Dropped, Joined, Left, OverBudget, Present, Received, TimedOut, Unreadable
from .finished import FinishedDays
from .history import DayHistory, asks_history
from .journal import Journal
from .machine import DmoMachine, presence_check_s
from .markets import DayMarket
from .results import RunResult

log = logging.getLogger("dmosim.dmo")


class MarketDay:
    """Runs the market days of one run on an open bus: the machine's events from Zenoh, its actions onto it.
    ``on_progress(phase, hour)`` is called as the clock advances; ``market`` is the machine's (markets.py; by
    default the one ``config`` describes)."""

    def __init__(self, bus: Bus, config: DayConfig, on_progress: Callable[[str, int | None], None] | None = None,
                 market: DayMarket | None = None):
        self.bus, self.config, self.market = bus, config, market
        self.events: queue.Queue = queue.Queue()
        self.on_progress = on_progress or (lambda phase, hour: None)
        self.journal: Journal | None = None
        self.history: DayHistory | None = None  # opened by run(), on the journal if there is one
        self.machine: DmoMachine | None = None  # made by run()
        self.budget = SenderBudget(*config.budget)  # what each agent may send in a phase or hour (messages/budget.py)
        bus.on_reject = lambda key, payload, err: self.events.put(Unreadable(key, payload, err))
        bus.tap = self._traffic
        bus.gate = self._admit

    @property
    def state(self):
        """The machine's state of the day (what it has accepted, where the run stands)."""
        return self.machine.state

    def run(self, before_start: Callable[[], None] | None = None) -> RunResult:
        """Run the days. ``before_start`` is called once the DMO listens and before its first message (to wait
        for a recorder, so that the recording misses nothing). A DMO restarted on its journal gives the days it
        had finished from the journal and runs again the phase, or hour, it had reached."""
        c = self.config
        finished = FinishedDays()
        if c.journal:
            self.journal = Journal(c.journal, self.bus.keys.run_id, c.market_day)
            if self.journal.entries:
                log.warning("resuming the run from %s", self.journal.path)
        self.machine = DmoMachine(c, secrets.token_hex(16), self.journal.entries if self.journal else None,
                                  self.market)
        self.bus.run_token = self.machine.state.run_token
        self.history = DayHistory(self.journal)
        self._listen()
        if before_start is not None:
            before_start()
        actions = self.machine.start(time.monotonic())
        while True:
            *done, request = actions
            for action in done:
                self._do(action, finished)
            if isinstance(request, Stop):
                break
            actions = self.machine.handle(self._answer(request), time.monotonic())
        self._await_recorder()
        if self.journal is not None:
            self.journal.close()
        days, realised = finished.read()
        return RunResult(days, c.rule.label, sorted(self.machine.state.registered), realised, self.machine.last)

    def _do(self, action, finished: FinishedDays) -> None:
        if isinstance(action, Publish):
            if isinstance(action.msg, Clock):
                self.on_progress(action.msg.phase, action.msg.hour)
            self.bus.publish(action.msg)
        elif isinstance(action, Journaled):
            if self.journal is not None:
                self.journal.write(action.entry)
        elif isinstance(action, Realised):
            finished.realised(action.msg)
        elif isinstance(action, Settled):
            finished.day(action.report)  # the day goes to disk before the next day's messages come
            return_free_memory()  # what the day's messages took from the C heap goes back to the OS
        else:
            raise TypeError(f"the DMO's driver cannot do {action!r}")

    def _answer(self, request):
        """The event that answers the machine's request."""
        if isinstance(request, OpenWindow):
            return Dropped(self.budget.next_window())
        if isinstance(request, CheckPresence):
            return Present(self._present(request))
        return self._next_event(request)

    def _present(self, check: CheckPresence) -> frozenset[str]:
        """Who of those asked about is present, asked until all are or ``wait_s`` have passed."""
        deadline, names = time.monotonic() + check.wait_s, set(check.names)
        while True:  # presence by a liveliness query: the event queue is left to the machine
            present = names & self.bus.present(timeout_s=check.query_s)
            if present == names or time.monotonic() >= deadline:
                return frozenset(present)
            time.sleep(0.2)

    def _next_event(self, wait: Wait):
        """The next event, or TimedOut once ``wait.until`` has passed with none; while it waits, every
        ``STILL_WAITING_S`` (halfway to a deadline on the wall clock), say for what and from whom."""
        start = time.monotonic()
        say_at = start + (STILL_WAITING_S if math.isinf(wait.until) else (wait.until - start) / 2)
        while True:
            now = time.monotonic()
            try:
                return self.events.get(timeout=max(0.0, min(wait.until, say_at) - now))
            except queue.Empty:
                pass
            now = time.monotonic()
            if now >= wait.until:
                return TimedOut()
            if now >= say_at:
                log.warning("%s: still waiting for %s from %s", self.machine.state.phase, wait.what,
                            ", ".join(wait.waiting))
                say_at = now + STILL_WAITING_S if math.isinf(wait.until) else wait.until

    def _await_recorder(self) -> None:
        """If a recorder is present, wait (at most ``RECORDER_CHECK_S``) until it has asked for the traffic to its
        end (it asks as agents leave): what the network lost on its way there, the last day's statements and summary
        too, reaches the recording."""
        recorder = RECORDER in self.bus.present(timeout_s=presence_check_s(self.config))
        if recorder and not self.history.wait_answered(RECORDER_CHECK_S):
            log.warning("the recorder did not ask for the run's last messages within %g s: the recording may lack "
                        "what the network lost on its way there", RECORDER_CHECK_S)

    def _listen(self) -> None:
        self.bus.subscribe(f"{self.bus.keys.prefix}/agent/**", lambda k, m, t, p: self.events.put(Received(k, m, p)),
                           payload=True)
        self.bus.watch_presence(lambda name: self.events.put(Joined(name)), lambda name: self.events.put(Left(name)))
        self.bus.serve(self.bus.keys.everything(), self.history.answer, slow=asks_history)

    def _traffic(self, key: str, payload: bytes, at: int) -> None:
        """Every payload sent or received (the bus's tap, on Zenoh's threads too): kept for late joiners."""
        if self.history is not None:
            self.history.record(key, payload, at)

    def _admit(self, key: str, size: int) -> bool:
        """Whether a payload received on ``key`` is within its sender's budget (the bus's gate, on Zenoh's threads):
        the first one over it in a phase or hour tells the day (one incident); it and the rest are dropped unread."""
        sender = agent_of(key)
        dropped = self.budget.admit(sender, size)
        if dropped == 1:
            self.events.put(OverBudget(sender))
        return not dropped


STILL_WAITING_S = 60.0  # on the logical clock, how often the DMO says who it is still waiting for
RECORDER_CHECK_S = 10.0  # how long a leaving DMO waits for the recorder to ask for what it may have missed
