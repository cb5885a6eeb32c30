"""The DMO's market days as a state machine without I/O, in the style of protocol libraries such as h11: events go
in (``handle``), actions come out (actions.py); no Zenoh, thread, queue or clock inside (docs/architecture.md).

The days read as the protocol does (docs/protocol.md): registration once, then each day the call for bids,
clearing, scheduling, 24 real-time hours and settlement. Each phase ends when every live registered agent has
answered (accepted, or refused: an agent told no is not waited for) or, on the wall clock, its deadline passes; on
the logical clock a phase has no deadline, so a loaded machine makes a run slower, never different
(docs/experiments.md, "Logical and wall-clock time"). What the day accepts is decided by intake.py, on the market's
rules (market/acceptance.py) and the replay guard (guard.py); what it publishes is built by outbox.py; its journal
entries (journal.py) let a restarted DMO resume the day, and rejoin.py decides what an agent that comes back is sent
again. A refused message is published on ``dmo/rejected`` with its reason, counted, and never changes an award or a
settlement.

The phases are written as one generator: each ``yield`` is a request to the driver (wait for events, ask who is
present, open a budget window) and receives its answer, the next event. The time of each event is the driver's
(``now``, seconds on its monotonic clock): it sets the wall clock's deadlines and measures the phases, and on the
logical clock changes nothing the market decides.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable, Generator

from messages import PHASES, GridState, make_receipt, make_rejection, sha256
from messages.codec import MessageError
from messages.keys import agent_of
from messages.schemas import AgentDay
from scenarios.horizon import HOURS

from ..market.acceptance import PHASE_ORDER
from ..market.settlement import DayTotals, Statement
from . import intake, outbox, rejoin
from .actions import (Action, CheckPresence, Journaled, OpenWindow, Publish, Realised, Request, Settled, Stop,
                      Wait)
from .config import DayConfig
from .events import Dropped, Event, Joined, Left, OverBudget, Present, Received, TimedOut, Unreadable
from .journal import accepted_entry, clock_entry, incident_entry, rejected_entry, restore, run_token_entry
from .markets import Clearing, DayMarket, LiveMarket
from .results import DayResult
from .state import DayState

log = logging.getLogger("dmosim.dmo")

Phase = Generator[Request, Event, None]


class NobodyRegistered(RuntimeError):
    """Registration closed, at its deadline on the wall clock, with no agent registered: the run cannot go on."""


class DmoMachine:
    """The market days of one run, of ``market`` (markets.py; by default the one ``config`` describes, clearing the
    bids it accepts). ``run_token`` is the run's token, drawn by the driver (a DMO resumed on its journal, whose
    ``journal`` entries are given, keeps the one they hold). ``start(now)`` gives the first actions;
    ``handle(event, now)`` the actions an event leads to. The last action of each is the request the next event
    answers, or ``Stop``: then the run is over, its days' reports were the ``Settled`` actions and its agents'
    realised days the ``Realised`` ones (the driver keeps them: ``RunResult``), and ``last`` is its last day's
    whole result."""

    def __init__(self, config: DayConfig, run_token: str, journal: list[dict] | None = None,
                 market: DayMarket | None = None):
        self.config = config
        self.market = market or LiveMarket(config)
        self.state = DayState(market_day=config.market_day)
        self.now = 0.0
        self.clearing: Clearing | None = None
        self.last: DayResult | None = None  # the last day's whole result, once the run is over
        self._actions: list[Action] = []
        self._grid: GridState | None = None  # the current hour's, re-sent to an agent that rejoins
        self._bids_due = 0.0
        self._returning: dict[str, float] = {}  # agent the run restarts -> until when it is waited for (now's clock)
        # (agent, kind, hour) of the answers refused in this phase or hour, and agents over their budget in it: an
        # agent told no does not send it again, so it is not waited for
        self._refused: set[tuple[str, str, int | None]] = set()
        self._over: set[str] = set()
        realised: list[AgentDay] = []
        # where the journal had the run, (phase, hour) of its day, run again from its start (None: a new run)
        self.resumed, self._closed = restore(self.state, journal or [], realised.append)
        self._actions.extend(Realised(msg) for msg in realised)
        if self.resumed is not None:
            log.warning("resuming the run from its journal: day %d %s, %d accepted messages", self.state.day,
                        _when(*self.resumed), sum(self.state.accepted.values()))
        if not self.state.run_token:  # a new run (a resumed one keeps the token its journal holds)
            self.state.run_token = run_token
            self._journal(run_token_entry(run_token))
        self._run = self._days()

    # --- the machine's interface ---------------------------------------------------------------------------------

    def start(self, now: float) -> list[Action]:
        """The actions of the run's start, up to its first request."""
        return self._step(None, now)

    def handle(self, event: Event, now: float) -> list[Action]:
        """The actions ``event`` (the answer to the last request) leads to, up to the next request."""
        return self._step(event, now)

    def _step(self, event: Event | None, now: float) -> list[Action]:
        self.now = now
        try:
            request = self._run.send(event)
        except StopIteration:
            request = Stop()
        actions, self._actions = self._actions, []
        actions.append(request)
        return actions

    # --- the days and their phases -----------------------------------------------------------------------------

    def _days(self) -> Phase:
        s, c = self.state, self.config
        yield from self._await_resumed_agents()
        while self._closed:  # the days a resumed DMO had finished: each goes out as its report, like any other
            self._actions.append(Settled(self._settled_again(self._closed.pop(0)).report()))
        last = None
        for day in range(s.day, c.days + 1):
            if day > s.day:
                self._actions.append(Settled(last.report()))  # the day before, before the next day's messages come
                last = None
                s.start_day(day, c.market_day_of(day))
            last = yield from self._day(day)
        yield from self._linger()
        if last is not None:  # the last day's report after lingering: it counts the realised days accepted meanwhile
            self._actions.append(Settled(last.report()))
        self.last = last

    def _day(self, day: int) -> Generator[Request, Event, DayResult]:
        s, c = self.state, self.config
        steps = dict(zip(PHASES, (self._registration, self._bidding, self._clearing, self._scheduling,
                                  self._realtime, self._settlement)))
        first = PHASE_ORDER["registration" if day == 1 else "bidding"]
        if self.resumed is not None:
            first = PHASE_ORDER[self.resumed[0]]
            if first > PHASE_ORDER["clearing"]:
                self.clearing = self.market.clear(s)
                if first == PHASE_ORDER["scheduling"]:  # some awards may not have gone out; agents ignore a repeat
                    self._publish_awards()
        timings = {}
        for phase in PHASES[first:]:
            start = self.now
            out = yield from steps[phase]()
            timings[phase] = self.now - start
        self.resumed = None
        statements, totals, locked_out = out
        return DayResult(day, s.market_day, c.islanded(day), self.clearing, statements, totals, copy.copy(s), timings,
                         locked_out)

    def _settled_again(self, closed: DayState) -> DayResult:
        """A day finished before the DMO restarted, settled again from its journal (nothing is published)."""
        clearing = self.market.clear(closed)
        statements, totals = self.market.settle(closed, clearing)
        return DayResult(closed.day, closed.market_day, self.config.islanded(closed.day), clearing, statements,
                         totals, closed, {})

    def _registration(self) -> Phase:
        s, c = self.state, self.config
        yield from self._clock("registration", c.registration_s)
        rule = self.market.registration(s)

        def accept(msg):
            refusal = rule(msg)
            if refusal is None:
                log.info("registered %s (%d/%d)", msg.sender, len(s.registered), c.agents)
            return refusal

        missing = lambda: [f"{c.agents - len(s.registered)} more agent(s)"] if len(s.registered) < c.agents else []
        yield from self._wait(c.registration_s, missing, "registration", accept, name_late=False)
        if len(s.registered) < c.agents:
            self._incident(None, f"only {len(s.registered)} of {c.agents} agents registered by the deadline")
        if not s.registered:
            raise NobodyRegistered("no agent registered before the registration deadline")

    def _bidding(self) -> Phase:
        s, c = self.state, self.config
        yield from self._clock("bidding", c.bids_s)
        self._bids_due = self.now + c.bids_s
        self._publish(self.market.call_for_bids(s.day, c.bids_s))
        yield from self._wait(c.bids_s, lambda: self._unanswered(s.bids, "bid"), "bid",
                              intake.first_of_each(s, s.bids))

    def _clearing(self) -> Phase:
        yield from self._clock("clearing", self.config.bids_s)
        self.clearing = self.market.clear(self.state)
        self._publish_awards()
        for msg in self.market.planned(self.state, self.clearing):  # after the awards: agents need not wait for it
            self._publish(msg)

    def _publish_awards(self) -> None:
        for agent in sorted(self.state.registered):
            self._publish(self.market.award(self.state, self.clearing, agent))

    def _scheduling(self) -> Phase:
        s, c = self.state, self.config
        yield from self._clock("scheduling", c.schedule_s)
        yield from self._wait(c.schedule_s, lambda: self._unanswered(s.schedules, "schedule"), "schedule",
                              intake.first_of_each(s, s.schedules))

    def _realtime(self) -> Phase:
        s, c = self.state, self.config
        first = self.resumed[1] if self.resumed and self.resumed[0] == "realtime" else 1
        grids = self.market.grid_states(s, self.clearing)  # once a day, from its clearing (a resumed day's too)
        for hour in range(first, HOURS + 1):
            yield from self._clock("realtime", c.hour_s, hour)
            self._grid = grids[hour - 1]
            self._publish(self._grid)
            accept = intake.meter_report(s, hour, c.subperiods, self._grid)
            yield from self._wait(c.hour_s, lambda: self._unanswered({a for a in s.meter if hour - 1 in s.meter[a]},
                                                                     "meter_report", hour),
                                  f"meter report for hour {hour}", accept)

    def _settlement(self) -> Generator[Request, Event, tuple[dict[str, Statement], DayTotals, tuple[str, ...]]]:
        s, c = self.state, self.config
        yield from self._clock("settlement", c.hour_s)
        # what arrived since the last hour closed is late, and recorded as such
        accept = intake.out_of_phase(s)
        while not isinstance(event := (yield Wait("what came late", (), -math.inf)), TimedOut):
            yield from self._handle(event, accept)
        locked_out = tuple(s.guard.locked_out())
        for agent in locked_out:
            self._incident(agent, "locked out: a process of it spoke to the DMO, which did not admit it (its "
                                  "registration was refused, or never came)")
        for incident in s.log.close(s.phase, s.hour):
            log.warning("settlement: %s", incident.reason)
        statements, totals = self.market.settle(s, self.clearing)
        for msg in self.market.realised(s):
            self._publish(msg)
        for st in statements.values():
            self._publish(self.market.statement(s, st))
        self._publish(outbox.day_summary(s.market_day, s.registered, self.clearing.price, statements, s.rejected,
                                         s.incidents))
        return statements, totals, locked_out

    def _linger(self) -> Phase:
        """Stay until the live agents have left (they leave once they have the summary and what they sent is
        receipted), on the wall clock at most ``linger_s`` (the hour deadline unless set): the DMO is the agents'
        router, and closing at once could cut off the summary still on its way. What agents send meanwhile is
        decided and receipted as in settlement: a realised day of the last day is still taken. An agent whose
        presence the DMO cannot see (a client that declares no liveliness token) is not waited for."""
        c, live = self.config, self.state.live()
        present: Present = yield CheckPresence(tuple(live), presence_check_s(self.config))
        waiting = set(live) & present.names
        until = self._deadline(c.hour_s if c.linger_s is None else c.linger_s)
        accept = intake.out_of_phase(self.state)
        while waiting:
            event = yield Wait("their leaving", tuple(sorted(waiting)), until)
            if isinstance(event, TimedOut):
                break
            if isinstance(event, Left):
                waiting.discard(event.name)
            elif not isinstance(event, Joined):
                yield from self._handle(event, accept)
        yield from self._next_window()

    # --- a restarted DMO, and agents that come and go ---------------------------------------------------------

    def _await_resumed_agents(self) -> Phase:
        """A resumed DMO waits (at most ``resume_wait_s``) for its agents to reconnect before it goes on; those
        that do not are noted gone, as vanished."""
        if self.resumed is None:
            return
        s = self.state
        present: Present = yield CheckPresence(tuple(sorted(s.registered)), 1.0, self.config.resume_wait_s)
        waiting = sorted(set(s.registered) - present.names)
        for agent in waiting:
            s.gone.add(agent)
            s.vanished[agent] = (s.phase, s.hour)
        self._incident(None, f"the DMO restarted and resumed day {s.day} {_when(*self.resumed)} from its journal "
                             f"({sum(s.accepted.values())} accepted messages recovered)"
                             + (f"; not back: {', '.join(waiting)}" if waiting else ""))

    def _joined(self, name: str) -> None:
        s = self.state
        if name in s.gone and name in s.registered:
            s.gone.discard(name)
            since = s.vanished.get(name, (s.phase, None))
            self._incident(name, f"reappeared after vanishing {_when(*since)}{_outage(since, s.hour)}; "
                                 f"sent {self._resend(name)}")

    def _left(self, name: str) -> Phase:
        s = self.state
        if name in s.registered and name not in s.gone:
            present: Present = yield CheckPresence((name,), presence_check_s(self.config))
            if name in present.names:
                return  # an earlier process of it left; a restarted one is here (their tokens share the key)
            s.gone.add(name)
            s.vanished[name] = (s.phase, s.hour)
            if name in self.config.restarting:  # the run restarts it: a new process is on its way
                self._returning[name] = self._deadline(self.config.registration_s)
            self._incident(name, "vanished (liveliness lost); what it does not report is settled by the "
                                 "missing-data rule")

    def _unanswered(self, answered, kind: str, hour: int | None = None) -> list[str]:
        """The agents a phase or hour still waits for (``_awaited``) that have neither an accepted answer (in
        ``answered``) nor one of ``kind`` (for ``hour``) refused, nor gone over their budget in it."""
        return [a for a in self._awaited()
                if a not in answered and (a, kind, hour) not in self._refused and a not in self._over]

    def _awaited(self) -> list[str]:
        """The agents a phase or hour waits for: the live ones, and one the run restarts (``restarting``) from when
        it vanishes until it is back (on the wall clock, at most until a new process of it would be past the
        registration deadline; a phase or hour still ends at its own deadline). Without this a fast day ran its
        remaining hours in a second while the restarted process was still starting, and settled it as missing for 11
        to 24 of them."""
        s = self.state
        back = [a for a, until in self._returning.items() if a in s.gone and self.now < until]
        return sorted({*s.live(), *back})

    def _resend(self, agent: str) -> str:
        """Send an agent that comes back what it needs to go on; say what was sent."""
        kinds, said = rejoin.resend_plan(self.state, agent, self.clearing is not None, self._grid is not None)
        for kind in kinds:
            if kind == rejoin.CALL_FOR_BIDS:
                due = self.config.bids_s if self.config.logical else round(max(0.1, self._bids_due - self.now), 1)
                self._publish(self.market.call_for_bids(self.state.day, due))
            elif kind == rejoin.AWARD:
                self._publish(self.market.award(self.state, self.clearing, agent))
            else:
                self._publish(self._grid)
        return said

    # --- events, waits and what the machine asks for -----------------------------------------------------------

    def _wait(self, seconds: float, waiting_for: Callable[[], list[str]], what: str, accept,
              name_late: bool = True) -> Phase:
        """Handle events until nobody is ``waiting_for`` or, on the wall clock, ``seconds`` pass; then name the late
        agents."""
        until = self._deadline(seconds)
        while waiting := waiting_for():
            event = yield Wait(what, tuple(waiting), until)
            if isinstance(event, TimedOut):
                for agent in waiting_for() if name_late else ():
                    self._incident(agent, f"late: no {what} by the deadline")
                return
            yield from self._handle(event, accept)

    def _handle(self, event: Event, accept) -> Phase:
        if isinstance(event, OverBudget):
            self._over.add(event.agent)
            messages, size = self.config.budget
            self._incident(event.agent, f"over its budget of {messages} messages and {size} bytes in this "
                                        f"{'hour' if self.state.hour else 'phase'}: what it sends more until the "
                                        "next is dropped unread (dropped_messages)")
        elif isinstance(event, Unreadable):
            self._reject(event.key, event.payload, event.error, agent_of(event.key))
        elif isinstance(event, Joined):
            self._joined(event.name)
        elif isinstance(event, Left):
            yield from self._left(event.name)
        elif isinstance(event, Received):
            self._received(event.key, event.msg, event.payload, accept)
        else:
            raise TypeError(f"the DMO's machine cannot handle {event!r} while it waits for messages")

    def _received(self, key: str, msg, payload: bytes, accept) -> None:
        """A valid message from an agent, with the bytes it arrived as, decided by ``intake.receive``: what it took
        is journaled before its receipt goes (what is receipted survives a restart), a refusal is published, a
        rejoin is met with what the agent needs; every message gets its receipt."""
        outcome = intake.receive(self.state, msg, sha256(payload), accept, self.config.network,
                                 self.config.placement)
        if outcome.what == intake.REFUSED:
            code, reason = outcome.refusal
            return self._reject(key, payload, MessageError(reason, code), msg.sender, msg)
        if outcome.taken:
            self._journal(accepted_entry(key, payload))
        if outcome.taken and isinstance(msg, AgentDay):
            self._actions.append(Realised(msg))
        self._publish(make_receipt(msg.sender, payload, None, market_day=self.state.market_day))
        if outcome.what == intake.REJOINED:
            self._incident(msg.sender, f"rejoined: a restarted process of it registered again; sent "
                                       f"{self._resend(msg.sender)}")

    def _reject(self, key: str, payload: bytes, err: MessageError, offender: str | None, msg=None) -> None:
        """A payload refused: counted, listed, published as a Rejection, and its sender (the agent the key names)
        gets the refusal as its receipt."""
        if (msg is not None and err.code not in REPLAYS
                and msg.incarnation == self.state.guard.incarnation.get(msg.sender)):
            # an answer of the agent's admitted process, refused: it will not send it again (a payload that could not
            # be read is no answer: its sender cannot tell the refusal is of it, and sends it again; nor is one of
            # another process in its name)
            self._refused.add((offender, msg.kind, msg.hour if msg.kind == "meter_report" else None))
        listed = self.state.log.count_rejection(err.code)
        self._journal(rejected_entry(err.code))
        if listed:
            self._incident(offender, f"rejected message on {key.split('/', 2)[-1]}: {err.code}: {err.reason}")
        else:
            log.info("rejected message on %s: %s: %s", key, err.code, err.reason)
        self._publish(make_rejection(key, payload, err, market_day=self.state.market_day, offender=offender))
        if offender is not None:
            self._publish(make_receipt(offender, payload, err, market_day=self.state.market_day))

    def _clock(self, phase: str, deadline_s: float, hour: int | None = None) -> Phase:
        s = self.state
        yield from self._next_window()
        s.phase, s.hour = phase, hour
        self._journal(clock_entry(phase, hour, s.day, s.market_day))
        self._publish(outbox.clock(self.config, s.day, phase, hour, deadline_s))

    def _next_window(self) -> Phase:
        """A new phase or hour: every agent's budget starts afresh; what the last window dropped of each is the
        day's ``dropped_messages``."""
        dropped: Dropped = yield OpenWindow()
        self.state.dropped.update({a: n for a, n in dropped.counts.items() if a is not None})
        self._refused, self._over = set(), set()

    def _incident(self, agent: str | None, reason: str) -> None:
        s = self.state
        incident = s.log.add(agent, s.phase, s.hour, reason)
        self._journal(incident_entry(incident))
        log.warning("%s%s: %s%s", s.phase, f" hour {s.hour}" if s.hour else "", f"{agent}: " if agent else "",
                    incident.reason)

    def _publish(self, msg) -> None:
        self._actions.append(Publish(msg))

    def _journal(self, entry: dict) -> None:
        self._actions.append(Journaled(entry))

    def _deadline(self, seconds: float) -> float:
        """When, on the driver's clock, a wait of ``seconds`` ends: never on the logical clock."""
        return math.inf if self.config.logical else self.now + seconds


PRESENCE_CHECK_S = 0.5  # how long a presence check may hold the DMO up (an answer on one host takes milliseconds) ...
PRESENCE_CHECK_LOGICAL_S = 30.0  # ... on the logical clock, where one that a loaded machine delays must not misjudge
# Refusals of what is not an agent's answer of now: a copy or replay of an earlier message, a message of a process of
# it that is gone, or one overtaken by a later one (guard.py). Its answer may still come, so it is still waited for.
REPLAYS = ("duplicate", "stale", "late")


def presence_check_s(config: DayConfig) -> float:
    """How long a presence check may take."""
    return PRESENCE_CHECK_LOGICAL_S if config.logical else PRESENCE_CHECK_S


def _when(phase: str, hour: int | None) -> str:
    return f"in {phase}" + (f" hour {hour}" if hour else "")


def _outage(since: tuple[str, int | None] | None, hour: int | None) -> str:
    """How many hours an agent that vanished ``since`` (phase, hour) was gone, if it came back in a later hour."""
    if since and since[1] and hour and hour > since[1]:
        return f", {hour - since[1]} hour(s) later"
    return ""
