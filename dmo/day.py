"""The DMO's market day (SPEC section 6): phases with deadlines, driven over a Bus, ending in settlement.

The DMO reads everything it receives from one queue on its main thread, so the day's state is touched by one
thread only; Zenoh's callback threads just enqueue. Each phase ends when every live registered agent has
answered or its deadline passes; late, duplicate, out-of-phase and foreign messages are rejected with a reason,
published on ``dmo/rejected`` for the recording, counted, and never change an award or a settlement.

Replays are caught by sequence number: a message whose (sender, seq) was already accepted is a ``duplicate``, one
older than the sender's latest accepted message is ``late`` (overtaken). An agent that vanishes (liveliness) and
comes back, reconnected or restarted (it then registers again, numbering from 0), is sent again what it needs to
go on; what it did not report is settled by the missing-data rule (docs/faults.md).
"""

from __future__ import annotations

import collections
import json
import logging
import queue
import time
from pathlib import Path
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from messages import (DMO, Award, Bid, CallForBids, Clock, DaySummary, GridState, Incident, MeterReport,
                      Registration, Schedule, SettlementStatement, StatementLine)
from messages.codec import MessageError, decode, encode, make_rejection
from messages.keys import check_agent_id
from messages.schemas import AgentTotals
from messages.transport import Bus

from .clearing import Bid as ClearingBid
from .clearing import ClearingResult, Step, clear, fixed_awards
from .settlement import Statement, settle

log = logging.getLogger("dmosim.dmo")

# Each rejection is an incident, up to this many; beyond, they are counted (and each is still published on
# dmo/rejected with its reason), so a flood of bad messages cannot swell the day summary past its limit.
MAX_LISTED_REJECTIONS = 200
MAX_INCIDENTS = 10_000

RULES_VERSION = 1
RULES = ("energy charge = clearing price x award per hour; penalty = c x max(P_M - P_sch, 0) x dt per sub-period; "
         "under-import credited at the credit rate (default 0); a missing sub-period is settled at P_M = the "
         "agent's registered max import with no credit (docs/market.md)")


@dataclass(frozen=True)
class DayConfig:
    """Everything the DMO needs to run one day. Deadlines are wall-clock seconds per phase (per hour in real
    time). ``fixed_awards`` (24 MW) replaces clearing by those awards for every agent (the paper's Table I)."""

    market_day: str
    agents: int
    iso_price: tuple[float, ...]
    import_limit: float
    export_limit: float
    penalty: float
    subperiods: int
    islanded_hours: tuple[int, ...]
    credit: float = 0.0
    fixed_awards: tuple[float, ...] | None = None
    price_floor: float = -1000.0
    price_cap: float = 10_000.0
    registration_s: float = 60.0
    bids_s: float = 600.0
    schedule_s: float = 1800.0
    hour_s: float = 300.0
    linger_s: float = 5.0  # after the summary, how long to wait for the agents to leave before closing
    journal: str | None = None  # where the DMO journals its day, to resume it if it is restarted
    resume_wait_s: float = 30.0  # a resumed DMO waits this long for its agents to reconnect


@dataclass
class DayState:
    """What the DMO has accepted so far; only the DMO's main thread touches it."""

    registered: dict[str, Registration] = field(default_factory=dict)
    gone: set[str] = field(default_factory=set)
    bids: dict[str, Bid] = field(default_factory=dict)
    schedules: dict[str, Schedule] = field(default_factory=dict)
    meter: dict[str, dict[int, tuple[float, ...]]] = field(default_factory=dict)
    incidents: list[Incident] = field(default_factory=list)
    rejected: int = 0
    rejected_by_code: collections.Counter = field(default_factory=collections.Counter)
    accepted: collections.Counter = field(default_factory=collections.Counter)  # by kind
    last_seq: dict[str, int] = field(default_factory=dict)   # per sender, of its last accepted message
    seqs: dict[str, set[int]] = field(default_factory=dict)  # per sender, the seqs of all its accepted messages
    vanished: dict[str, tuple[str, int | None]] = field(default_factory=dict)  # since (phase, hour); may rejoin
    rescheduling: set[str] = field(default_factory=set)      # rejoined agents whose new schedule is awaited
    phase: str = "registration"
    hour: int | None = None

    def live(self) -> list[str]:
        return sorted(a for a in self.registered if a not in self.gone)


class Journal:
    """The DMO's own record of its day, one JSON object a line, written as it goes: every clock step, every message
    it accepted, every incident and rejection. A DMO restarted on the same journal, run and market day reads it
    back and resumes the day where it stopped (a journal of another run is overwritten). Each line reaches the
    OS at once, so a DMO killed with SIGKILL loses nothing it had acted on."""

    def __init__(self, path: str | Path, run_id: str, market_day: str):
        self.path, self.head = Path(path), {"journal": 1, "run_id": run_id, "market_day": market_day}
        self.entries: list[dict] = []
        if self.path.exists():
            lines = self.path.read_text(errors="replace").splitlines()
            try:
                same = bool(lines) and json.loads(lines[0]) == self.head
            except ValueError:
                same = False
            for line in lines[1:] if same else ():
                try:
                    self.entries.append(json.loads(line))
                except ValueError:  # a line cut by the kill: the ones before it stand
                    break
        self._file = open(self.path, "a" if self.entries else "w", buffering=1)  # noqa: SIM115  (closed by close)
        if not self.entries:
            self.write(self.head)

    def write(self, entry: dict) -> None:
        self._file.write(json.dumps(entry, separators=(",", ":")) + "\n")

    def close(self) -> None:
        self._file.close()


@dataclass(frozen=True)
class DayResult:
    clearing: ClearingResult
    statements: dict[str, Statement]
    summary: DaySummary
    state: DayState
    phase_s: dict[str, float]


def island_hours(start: int, hours: int) -> tuple[int, ...]:
    """The hours start..start+hours-1 of one islanding event (none if ``hours`` is 0)."""
    return tuple(range(start, start + hours)) if hours else ()


def draw_islanding(hours: int, seed: int) -> tuple[int, ...]:
    """One islanding event of ``hours`` whole hours at a seeded uniform start, as the scenarios draw them."""
    if not hours:
        return ()
    start = 1 + int(np.random.default_rng([seed, 7]).integers(0, 25 - hours))
    return island_hours(start, hours)


class MarketDay:
    """Runs one day on an open bus. ``on_progress(phase, hour)`` is called as the clock advances."""

    def __init__(self, bus: Bus, config: DayConfig, on_progress: Callable[[str, int | None], None] | None = None):
        self.bus, self.config = bus, config
        self.state = DayState()
        self.events: queue.Queue = queue.Queue()
        self.on_progress = on_progress or (lambda phase, hour: None)
        self.clearing: ClearingResult | None = None
        self._grid: GridState | None = None  # the current hour's, re-sent to an agent that rejoins
        self.journal: Journal | None = None
        self._resumed: tuple[str, int | None] | None = None
        bus.on_reject = lambda key, payload, err: self.events.put(("reject", key, payload, err))

    # --- plumbing ------------------------------------------------------------------------------------------

    def _listen(self) -> None:
        self.bus.subscribe(f"{self.bus.keys.prefix}/agent/**", lambda k, m, t: self.events.put(("msg", k, m, t)))
        self.bus.watch_presence(lambda name: self.events.put(("join", name)),
                                lambda name: self.events.put(("leave", name)))

    def _publish(self, msg) -> None:
        self.bus.publish(msg)

    def _clock(self, phase: str, deadline_s: float, hour: int | None = None) -> None:
        self.state.phase, self.state.hour = phase, hour
        self._journal({"clock": phase, "hour": hour})
        self.on_progress(phase, hour)
        self._publish(Clock(sender=DMO, market_day=self.config.market_day, phase=phase, hour=hour,
                            deadline_s=deadline_s))

    def _incident(self, agent: str | None, reason: str) -> None:
        s = self.state
        s.incidents.append(Incident(agent=agent, phase=s.phase, hour=s.hour, reason=reason[:500]))
        self._journal({"incident": s.incidents[-1].model_dump()})
        log.warning("%s%s: %s%s", s.phase, f" hour {s.hour}" if s.hour else "", f"{agent}: " if agent else "", reason)

    def _reject(self, key: str, payload: bytes, err: MessageError, offender: str | None) -> None:
        s = self.state
        s.rejected += 1
        s.rejected_by_code[err.code] += 1
        self._journal({"rejected": err.code})
        if s.rejected <= MAX_LISTED_REJECTIONS:
            self._incident(offender, f"rejected message on {key.split('/', 2)[-1]}: {err.code}: {err.reason}")
        else:
            log.info("rejected message on %s: %s: %s", key, err.code, err.reason)
        self._publish(make_rejection(key, payload, err, market_day=self.config.market_day, offender=offender))

    def _refuse(self, key: str, msg, code: str, reason: str) -> None:
        from messages import encode  # noqa: PLC0415  (only needed for the rare refusal)

        self._reject(key, encode(msg), MessageError(reason, code), msg.sender)

    def _wait(self, deadline: float, waiting_for: Callable[[], list[str]], what: str, accept,
              name_late: bool = True) -> None:
        """Handle events until nobody is ``waiting_for`` or the deadline passes; then name the late agents.

        Halfway to the deadline the DMO logs who it is waiting for, so a stall is never silent.
        """
        warned = False
        start = time.monotonic()
        while waiting_for():
            now = time.monotonic()
            if now >= deadline:
                for agent in waiting_for() if name_late else ():
                    self._incident(agent, f"late: no {what} by the deadline")
                return
            if not warned and now >= start + (deadline - start) / 2:
                log.warning("%s: still waiting for %s from %s", self.state.phase, what, ", ".join(waiting_for()))
                warned = True
            try:
                event = self.events.get(timeout=min(deadline - now, max(0.05, (deadline - start) / 2 - (now - start))))
            except queue.Empty:
                continue
            self._handle(event, accept)

    def _handle(self, event, accept) -> None:
        kind = event[0]
        if kind == "reject":
            _, key, payload, err = event
            self._reject(key, payload, err, _offender(key))
        elif kind == "join":
            s, name = self.state, event[1]
            if name in s.gone and name in s.registered:
                s.gone.discard(name)
                since = s.vanished.get(name, (s.phase, None))
                self._incident(name, f"reappeared after vanishing {_when(*since)}{_outage(since, s.phase, s.hour)}; "
                                     f"sent {self._resend(name)}")
        elif kind == "leave":
            s, name = self.state, event[1]
            if name in s.registered and name not in s.gone:
                s.gone.add(name)
                s.vanished[name] = (s.phase, s.hour)
                self._incident(name, "vanished (liveliness lost); what it does not report is settled by the "
                                     "missing-data rule")
        else:
            _, key, msg, _ = event
            s = self.state
            reason = self._check(msg)
            if reason:
                return self._refuse(key, msg, *reason)
            before = s.rejected
            if isinstance(msg, Registration) and msg.sender in s.registered:
                self._rejoin(key, msg)
            elif isinstance(msg, Schedule) and msg.sender in s.rescheduling:
                s.schedules[msg.sender] = msg
                s.rescheduling.discard(msg.sender)
                log.info("%s rescheduled after rejoining", msg.sender)
            else:
                accept(key, msg)
            if s.rejected == before:
                self._accepted(msg)
                self._journal({"accepted": key, "message": encode(msg).decode()})

    def _accepted(self, msg) -> None:
        """Count an accepted message: a copy of it, or anything older from its sender, is stale from now on."""
        s = self.state
        s.last_seq[msg.sender] = max(msg.seq, s.last_seq.get(msg.sender, msg.seq))
        s.seqs.setdefault(msg.sender, set()).add(msg.seq)
        s.accepted[msg.kind] += 1

    def _journal(self, entry: dict) -> None:
        if self.journal is not None:
            self.journal.write(entry)

    def _restore(self) -> None:
        """Rebuild the day from the journal of a DMO that was stopped: what it accepted, its incidents and
        rejections, and the phase (and hour) it had reached, which is then run again from its start."""
        s = self.state
        entries, self.journal.entries = self.journal.entries, []
        clock = None
        for entry in entries:
            if "clock" in entry:
                clock = (entry["clock"], entry["hour"])
            elif "incident" in entry:
                s.incidents.append(Incident(**entry["incident"]))
            elif "rejected" in entry:
                s.rejected += 1
                s.rejected_by_code[entry["rejected"]] += 1
            elif "accepted" in entry:
                msg = decode(entry["message"].encode())
                if isinstance(msg, Registration):
                    if msg.sender in s.registered:  # it rejoined: a new process, numbering from 0
                        s.seqs.pop(msg.sender, None)
                        s.last_seq.pop(msg.sender, None)
                    s.registered.setdefault(msg.sender, msg)
                    s.meter.setdefault(msg.sender, {})
                elif isinstance(msg, Bid):
                    s.bids[msg.sender] = msg
                elif isinstance(msg, Schedule):
                    s.schedules[msg.sender] = msg
                elif isinstance(msg, MeterReport):
                    s.meter[msg.sender][msg.hour - 1] = msg.p_m_mw
                self._accepted(msg)
        if clock is None:
            return
        self._resumed = clock
        s.phase, s.hour = clock
        log.warning("resuming the day from %s: %s, %d accepted messages", self.journal.path, _when(*clock),
                    sum(s.accepted.values()))

    def _check(self, msg) -> tuple[str, str] | None:
        s = self.state
        if msg.market_day != self.config.market_day:
            return "wrong_day", f"market day {msg.market_day}, expected {self.config.market_day}"
        if not isinstance(msg, Registration) and msg.sender not in s.registered:
            return "unregistered", f"{msg.sender} is not registered"
        # A restarted agent numbers its messages from 0 again: its re-registration after vanishing is let through.
        if isinstance(msg, Registration) and msg.sender in s.vanished:
            return None
        if msg.seq in s.seqs.get(msg.sender, ()):
            return "duplicate", f"{msg.sender}'s message #{msg.seq} was already accepted: a duplicate or a replay"
        last = s.last_seq.get(msg.sender)
        if last is not None and msg.seq < last:
            return "late", (f"{msg.sender}'s message #{msg.seq} is older than its message #{last}, already accepted: "
                            "overtaken (delayed or replayed)")
        return None

    def _out_of_phase(self, key, msg) -> None:
        if isinstance(msg, Registration):
            return self._refuse(key, msg, "late", f"registration is closed (now {self.state.phase}): {msg.sender} "
                                                  "is not an agent of this day")
        code = "late" if _PHASE_OF.get(msg.kind, 99) < _ORDER[self.state.phase] else "invalid"
        self._refuse(key, msg, code, f"{msg.kind} is out of phase (now {self.state.phase})")

    def _rejoin(self, key, msg: Registration) -> None:
        """A registered agent registers again: after vanishing (its process restarted), it rejoins and is sent
        again what it needs to go on: the call for bids while bidding, else its award and, in real time, the
        current hour's grid state. Hours it does not report are settled by the missing-data rule."""
        s, agent = self.state, msg.sender
        if agent not in s.vanished:
            return self._refuse(key, msg, "duplicate", f"{agent} is already registered")
        first = s.registered[agent]
        if (msg.case, msg.max_import_mw, msg.max_export_mw) != (first.case, first.max_import_mw, first.max_export_mw):
            return self._refuse(key, msg, "invalid", f"{agent} cannot rejoin: it registered again with another case "
                                                     "or other limits than at first")
        if s.phase == "settlement":
            return self._refuse(key, msg, "late", f"{agent} cannot rejoin: the day is being settled")
        del s.vanished[agent]
        s.gone.discard(agent)
        s.seqs.pop(agent, None)  # the new process numbers its messages from 0
        s.last_seq.pop(agent, None)
        if s.phase in ("scheduling", "realtime"):
            s.rescheduling.add(agent)
        self._incident(agent, f"rejoined after vanishing (registered again); sent {self._resend(agent)}")

    def _resend(self, agent: str) -> str:
        """Send an agent that comes back (reconnected, or restarted) what it needs to go on; say what was sent.
        Agents take what they already have as a no-op, so a broadcast sent again harms no one."""
        s = self.state
        if s.phase == "bidding":
            if agent in s.bids:
                return "nothing: its bid stands"
            self._publish(self._call_for_bids(again=True))
            return "the call for bids again"
        if s.phase in ("scheduling", "realtime") and self.clearing is not None:
            self._publish(self._award(agent))
            if s.phase == "realtime" and self._grid is not None:
                self._publish(self._grid)
                return f"its award and the grid state of hour {s.hour} again"
            return "its award again"
        return "nothing: registration is open" if s.phase == "registration" else "nothing"

    # --- phases --------------------------------------------------------------------------------------------

    def run(self, before_start: Callable[[], None] | None = None) -> DayResult:
        """Run the day. ``before_start`` is called once the DMO listens and before its first message (to wait
        for a recorder, so that the recording misses nothing)."""
        if self.config.journal:
            self.journal = Journal(self.config.journal, self.bus.keys.run_id, self.config.market_day)
            self._restore()
        self._listen()
        if before_start is not None:
            before_start()
        steps = (("registration", self._registration), ("bidding", self._bidding), ("clearing", self._clearing),
                 ("scheduling", self._scheduling), ("realtime", self._realtime), ("settlement", self._settlement))
        first = 0
        if self._resumed is not None:
            first = _ORDER[self._resumed[0]]
            self._await_agents()
            if first > _ORDER["clearing"]:
                self._clear()
                if first == _ORDER["scheduling"]:  # some awards may not have gone out; agents ignore a repeat
                    for agent in sorted(self.state.registered):
                        self._publish(self._award(agent))
        timings = {}
        for phase, step in steps[first:]:
            start = time.monotonic()
            out = step()
            timings[phase] = time.monotonic() - start
        statements, summary, clearing = out
        self._linger()
        if self.journal is not None:
            self.journal.close()
        return DayResult(clearing, statements, summary, self.state, timings)

    def _await_agents(self) -> None:
        """A resumed DMO waits (at most ``resume_wait_s``) for its agents to reconnect before it goes on; those
        that do not are noted gone, as vanished."""
        s, c = self.state, self.config
        deadline = time.monotonic() + c.resume_wait_s
        while True:  # presence by a liveliness query: the event queue is left to the phase
            waiting = set(s.registered) - self.bus.present(timeout_s=1.0)
            if not waiting or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
        for agent in sorted(waiting):
            s.gone.add(agent)
            s.vanished[agent] = (s.phase, s.hour)
        self._incident(None, f"the DMO restarted and resumed the day {_when(*self._resumed)} from its journal "
                             f"({sum(s.accepted.values())} accepted messages recovered)"
                             + (f"; not back: {', '.join(sorted(waiting))}" if waiting else ""))

    def _linger(self) -> None:
        """Stay until the live agents have left (they leave once they have the summary), at most ``linger_s``:
        the DMO is the agents' router, and closing at once could cut off the summary still on its way."""
        waiting = set(self.state.live())
        deadline = time.monotonic() + self.config.linger_s
        while waiting and (left := deadline - time.monotonic()) > 0:
            try:
                event = self.events.get(timeout=left)
            except queue.Empty:
                break
            if event[0] == "leave":
                waiting.discard(event[1])

    def _registration(self):
        s, c = self.state, self.config
        self._clock("registration", c.registration_s)

        def accept(key, msg):
            if isinstance(msg, Registration) and msg.sender not in s.registered:
                s.registered[msg.sender] = msg
                s.meter[msg.sender] = {}
                log.info("registered %s (%d/%d)", msg.sender, len(s.registered), c.agents)
            elif isinstance(msg, Registration):
                self._refuse(key, msg, "duplicate", f"{msg.sender} is already registered")
            else:
                self._out_of_phase(key, msg)

        missing = lambda: [f"{c.agents - len(s.registered)} more agent(s)"] if len(s.registered) < c.agents else []
        self._wait(time.monotonic() + c.registration_s, missing, "registration", accept, name_late=False)
        if len(s.registered) < c.agents:
            self._incident(None, f"only {len(s.registered)} of {c.agents} agents registered by the deadline")
        if not s.registered:
            raise RuntimeError("no agent registered before the registration deadline")

    def _bidding(self):
        s, c = self.state, self.config
        self._clock("bidding", c.bids_s)
        self._bids_due = time.monotonic() + c.bids_s
        self._publish(self._call_for_bids())

        self._wait(self._bids_due, lambda: [a for a in s.live() if a not in s.bids], "bid",
                   self._first_of_each(Bid, s.bids, "bid"))

    def _call_for_bids(self, again: bool = False) -> CallForBids:
        """The day's terms; sent ``again`` (to an agent that comes back), with the time left until bids are due."""
        c = self.config
        due = round(max(0.1, self._bids_due - time.monotonic()), 1) if again else c.bids_s
        return CallForBids(sender=DMO, market_day=c.market_day, iso_price_per_mwh=c.iso_price,
                           price_floor_per_mwh=c.price_floor, price_cap_per_mwh=c.price_cap,
                           import_limit_mw=c.import_limit, export_limit_mw=c.export_limit, penalty_per_mwh=c.penalty,
                           credit_per_mwh=c.credit, subperiods=c.subperiods, deadline_s=due)

    def _award(self, agent: str) -> Award:
        c = self.config
        return Award(sender=DMO, market_day=c.market_day, agent=agent, p_sch_mw=self.clearing.awards[agent],
                     clearing_price_per_mwh=self.clearing.price, penalty_per_mwh=c.penalty, credit_per_mwh=c.credit,
                     subperiods=c.subperiods, rules_version=RULES_VERSION, rules=RULES)

    def _clearing(self):
        self._clock("clearing", self.config.bids_s)
        self._clear()
        for agent in sorted(self.state.registered):
            self._publish(self._award(agent))

    def _clear(self) -> None:
        """Clear the accepted bids (a pure function of them: a resumed DMO gets the same awards again)."""
        s, c = self.state, self.config
        agents = sorted(s.registered)
        if c.fixed_awards is not None:
            self.clearing = fixed_awards({a: c.fixed_awards for a in agents}, c.iso_price)
        else:
            bids = [ClearingBid(a, tuple(tuple(Step(st.price_per_mwh, st.quantity_mw) for st in hour)
                                         for hour in s.bids[a].hours)) for a in sorted(s.bids)]
            self.clearing = clear(bids, c.iso_price, c.import_limit, c.export_limit, agents=agents)

    def _first_of_each(self, kind, store: dict, what: str):
        """Accept the first ``kind`` message of each agent into ``store``; refuse repeats and other kinds."""

        def accept(key, msg):
            if not isinstance(msg, kind):
                self._out_of_phase(key, msg)
            elif msg.sender in store:
                self._refuse(key, msg, "duplicate", f"second {what} from {msg.sender}; the first one stands")
            else:
                store[msg.sender] = msg

        return accept

    def _scheduling(self):
        s, c = self.state, self.config
        self._clock("scheduling", c.schedule_s)

        self._wait(time.monotonic() + c.schedule_s, lambda: [a for a in s.live() if a not in s.schedules],
                   "schedule", self._first_of_each(Schedule, s.schedules, "schedule"))

    def _realtime(self):
        s, c = self.state, self.config
        first = self._resumed[1] if self._resumed and self._resumed[0] == "realtime" else 1
        for hour in range(first, 25):
            self._clock("realtime", c.hour_s, hour)
            connected = hour not in c.islanded_hours
            self._grid = GridState(sender=DMO, market_day=c.market_day, hour=hour, subperiods=c.subperiods,
                                   connected=(connected,) * c.subperiods)
            self._publish(self._grid)

            def accept(key, msg, hour=hour):
                if not isinstance(msg, MeterReport):
                    return self._out_of_phase(key, msg)
                if msg.subperiods != c.subperiods:
                    return self._refuse(key, msg, "invalid", f"{msg.subperiods} sub-periods, the day has {c.subperiods}")
                if msg.hour != hour:
                    code = "late" if msg.hour < hour else "invalid"
                    return self._refuse(key, msg, code, f"meter report for hour {msg.hour} during hour {hour}")
                if (hour - 1) in s.meter[msg.sender]:
                    return self._refuse(key, msg, "duplicate", f"second meter report for hour {hour}")
                cap = s.registered[msg.sender].max_import_mw
                if max(msg.p_m_mw) > cap + 1e-9:
                    return self._refuse(key, msg, "invalid", f"P_M {max(msg.p_m_mw)} MW above registered max {cap}")
                s.meter[msg.sender][hour - 1] = msg.p_m_mw

            self._wait(time.monotonic() + c.hour_s, lambda: [a for a in s.live() if (hour - 1) not in s.meter[a]],
                       f"meter report for hour {hour}", accept)
        return None

    def _settlement(self):
        s, c = self.state, self.config
        self._clock("settlement", c.hour_s)
        while not self.events.empty():  # what arrived since the last hour closed is late, and recorded as such
            self._handle(self.events.get_nowait(), lambda key, msg: self._out_of_phase(key, msg))
        if s.rejected > MAX_LISTED_REJECTIONS:
            by_code = ", ".join(f"{code} {n}" for code, n in sorted(s.rejected_by_code.items()))
            self._incident(None, f"{s.rejected} messages rejected in all ({by_code}); only the first "
                                 f"{MAX_LISTED_REJECTIONS} are listed here, each is on dmo/rejected with its reason")
        if len(s.incidents) > MAX_INCIDENTS:
            extra = len(s.incidents) - MAX_INCIDENTS + 1
            del s.incidents[MAX_INCIDENTS - 1:]
            self._incident(None, f"{extra} more incidents not listed (see the DMO's log)")
        statements, summary = settle(self.clearing.awards, self.clearing.price, s.meter, subperiods=c.subperiods,
                                     penalty=c.penalty, credit=c.credit,
                                     p_m_max={a: r.max_import_mw for a, r in s.registered.items()})
        for agent, st in statements.items():
            self._publish(statement_message(st, c))
        self._publish(DaySummary(
            sender=DMO, market_day=c.market_day, agents=tuple(sorted(s.registered)),
            clearing_price_per_mwh=self.clearing.price,
            totals={a: AgentTotals(energy_charge=float(st.energy_charge), deviation_penalty=float(st.deviation_penalty),
                                   deviation_credit=float(st.credit), total=float(st.total))
                    for a, st in statements.items()},
            rejected_messages=s.rejected, incidents=tuple(s.incidents)))
        return statements, summary, self.clearing


_ORDER = {"registration": 0, "bidding": 1, "clearing": 2, "scheduling": 3, "realtime": 4, "settlement": 5}
_PHASE_OF = {"registration": 0, "bid": 1, "schedule": 3, "meter_report": 4}


def _when(phase: str, hour: int | None) -> str:
    return f"in {phase}" + (f" hour {hour}" if hour else "")


def _outage(since: tuple[str, int | None] | None, phase: str, hour: int | None) -> str:
    if since and since[1] and hour and hour > since[1]:
        return f", {hour - since[1]} hour(s) later"
    return ""


def _offender(key: str) -> str | None:
    """The agent a refused payload's key names, if it names one: any text can arrive there, and only a valid
    agent id may go into an incident or a Rejection."""
    parts = key.split("/")
    if len(parts) > 3 and parts[2] == "agent":
        try:
            return check_agent_id(parts[3])
        except ValueError:
            return None
    return None


def statement_message(st: Statement, c: DayConfig) -> SettlementStatement:
    """A settlement Statement as the message the DMO publishes (hours 1..24 on the wire)."""
    lines = tuple(StatementLine(hour=line.hour + 1, p_sch_mw=line.award_mwh, clearing_price_per_mwh=line.price,
                                energy_charge=float(line.energy_charge), import_mwh=line.import_mwh,
                                deviation_mwh=line.deviation_mwh, under_import_mwh=line.under_import_mwh,
                                deviation_penalty=float(line.penalty), deviation_credit=float(line.credit),
                                total=float(line.total), missing=line.missing,
                                missing_subperiods=line.missing_subperiods) for line in st.lines)
    return SettlementStatement(sender=DMO, market_day=c.market_day, agent=st.agent, penalty_per_mwh=c.penalty,
                               credit_per_mwh=c.credit, rules_version=RULES_VERSION, lines=lines,
                               energy_charge=float(st.energy_charge), deviation_penalty=float(st.deviation_penalty),
                               deviation_credit=float(st.credit), total=float(st.total),
                               missing_subperiods=st.missing_subperiods)
