"""What an observer of a run knows, message by message: ``Observed.take(key, msg, at_ns)`` folds one valid message
of the run into it, with no I/O, thread or clock of its own, so a live run and a recording played into it give the
same state (``page.py`` turns it into what the page shows).

Messages are taken as the recording's readers take them (dmosim/results/tables.py): the first award, statement
and grid state of each agent or hour, the first meter report of each agent and hour, the last day summary; a
message of another run (its token not the first clock's) is ignored. A new market day starts on its first clock;
what the days before settled stays as each agent's bill so far.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from scenarios.horizon import HOURS

KEPT_INCIDENTS = 200  # the incidents kept (the latest): a page, not the recording


@dataclass
class SeenFeeder:
    """A feeder's day as the DMO's network hours say it: per (hour, stage) what the page draws."""

    network: str
    buses: tuple[str, ...]
    lines: tuple[str, ...]
    hours: dict[tuple[int, str], dict] = field(default_factory=dict)


@dataclass
class Day:
    """One market day as observed so far."""

    market_day: str
    iso_price: list[float | None] = field(default_factory=lambda: [None] * HOURS)
    subperiods: int = 1
    penalty_rate: float = 0.0
    credit_rate: float = 0.0
    awards: dict[str, tuple[float, ...]] = field(default_factory=dict)
    prices: dict[str, tuple[float, ...]] = field(default_factory=dict)  # each agent's clearing price (its bus's)
    bus_of: dict[str, str | None] = field(default_factory=dict)
    congestion: list[str | None] = field(default_factory=lambda: [None] * HOURS)
    bids: set[str] = field(default_factory=set)
    schedules: set[str] = field(default_factory=set)
    meter: dict[str, dict[int, tuple[float, ...]]] = field(default_factory=dict)  # agent -> hour -> P_M per sub-period
    connected: dict[int, tuple[bool, ...]] = field(default_factory=dict)
    statements: dict[str, dict] = field(default_factory=dict)  # agent -> its statement's totals and lines
    summary: dict | None = None
    feeder: SeenFeeder | None = None


@dataclass
class SeenClock:
    phase: str
    hour: int | None
    day: int
    days: int
    deadline_s: float
    at_ns: int  # when it came


class Observed:
    """The run as an observer has seen it: the clock, the registered agents, the current market day, the bills of the
    days before, the incidents. ``take`` is the only way in."""

    def __init__(self):
        self.run_token: str | None = None
        self.clock: SeenClock | None = None
        self.agents: dict[str, dict] = {}  # id -> {"incarnation", "bus", "strategy"}, in order of registration
        self.day: Day | None = None
        self.days_done: list[str] = []
        self.settled_before: dict[str, dict[str, float]] = {}  # agent -> totals of the days settled before this one
        self.incidents: list[dict] = []
        self.incident_count = 0
        self.rejected = 0
        self.messages = 0
        self.last_ns = 0

    # --- the one way in -------------------------------------------------------------------------------------------
    def take(self, key: str, msg, at_ns: int) -> bool:
        """Fold one valid message (``key`` relative to the run prefix, e.g. ``agent/mg1/meter``) in; False if it was
        not of this run. ``at_ns`` is when it was received (or recorded)."""
        if msg.kind == "clock" and self.run_token is None:
            self.run_token = msg.run
        if self.run_token is not None and msg.run and msg.run != self.run_token:
            return False
        self.messages += 1
        self.last_ns = max(self.last_ns, at_ns)
        if msg.kind == "registration":
            self._registration(msg, at_ns)
            return True
        if msg.kind == "rejection":
            self.rejected += 1
            self._incident(at_ns, msg.offender, self.clock.phase if self.clock else "registration",
                           self.clock.hour if self.clock else None, f"rejected {msg.rejected_kind or 'payload'} "
                           f"({msg.code}): {msg.reason}")
            return True
        if msg.kind == "clock":
            self._clock(msg, at_ns)
            return True
        day = self._day(msg.market_day)
        handler = getattr(self, "_" + msg.kind, None)
        if handler is not None:
            handler(day, msg, at_ns)
        return True

    # --- per kind ---------------------------------------------------------------------------------------------------
    def _registration(self, msg, at_ns: int) -> None:
        known = self.agents.get(msg.sender)
        if known is not None and msg.incarnation > known["incarnation"]:
            self._incident(at_ns, msg.sender, self.clock.phase if self.clock else "registration",
                           self.clock.hour if self.clock else None, "restarted: registered again (a rejoin)")
        if known is None or msg.incarnation >= known["incarnation"]:
            self.agents[msg.sender] = {"incarnation": msg.incarnation, "bus": msg.bus, "strategy": msg.strategy}

    def _clock(self, msg, at_ns: int) -> None:
        self._day(msg.market_day)
        self.clock = SeenClock(msg.phase, msg.hour, msg.day, msg.days, msg.deadline_s, at_ns)

    def _call_for_bids(self, day: Day, msg, at_ns: int) -> None:
        day.iso_price = list(msg.iso_price_per_mwh)
        day.subperiods = msg.subperiods
        day.penalty_rate, day.credit_rate = msg.penalty_per_mwh, msg.credit_per_mwh

    def _bid(self, day: Day, msg, at_ns: int) -> None:
        day.bids.add(msg.sender)

    def _schedule(self, day: Day, msg, at_ns: int) -> None:
        day.schedules.add(msg.sender)

    def _award(self, day: Day, msg, at_ns: int) -> None:
        if msg.agent in day.awards:
            return
        day.awards[msg.agent] = tuple(msg.p_sch_mw)
        day.prices[msg.agent] = tuple(msg.clearing_price_per_mwh)
        day.bus_of[msg.agent] = msg.bus
        day.subperiods = msg.subperiods
        day.penalty_rate, day.credit_rate = msg.penalty_per_mwh, msg.credit_per_mwh
        if msg.congestion is not None:
            day.congestion = list(msg.congestion)

    def _grid_state(self, day: Day, msg, at_ns: int) -> None:
        if msg.hour in day.connected:
            return
        day.connected[msg.hour] = tuple(msg.connected)
        if not all(msg.connected):
            off = sum(1 for c in msg.connected if not c)
            self._incident(at_ns, None, "realtime", msg.hour, f"islanded: {off} of {len(msg.connected)} sub-period(s) "
                                                              "not connected")

    def _meter_report(self, day: Day, msg, at_ns: int) -> None:
        day.meter.setdefault(msg.sender, {}).setdefault(msg.hour, tuple(msg.p_m_mw))

    def _network_hour(self, day: Day, msg, at_ns: int) -> None:
        if day.feeder is None:
            day.feeder = SeenFeeder(msg.network, tuple(msg.buses), tuple(msg.lines))
        if (msg.hour, msg.stage) in day.feeder.hours:
            return
        binding = msg.limit_loading
        day.feeder.hours[msg.hour, msg.stage] = {
            "voltage_pu": list(msg.voltage_pu), "line_loading": list(msg.line_loading),
            "bus_price_per_mwh": None if msg.bus_price_per_mwh is None else list(msg.bus_price_per_mwh),
            "energy_price_per_mwh": msg.energy_price_per_mwh,
            "binding_lines": [] if binding is None else [i for i, x in enumerate(binding) if x >= 1 - 1e-6],
            "violations": list(msg.ac.violations), "ac_v_min_pu": msg.ac.v_min_pu, "ac_max_loading": msg.ac.max_loading,
            "converged": msg.ac.converged}
        if msg.ac.violations:
            self._incident(at_ns, None, "realtime" if msg.stage == "realised" else "clearing", msg.hour,
                           f"AC check of the {msg.stage} hour: " + "; ".join(msg.ac.violations))

    def _settlement_statement(self, day: Day, msg, at_ns: int) -> None:
        if msg.agent in day.statements:
            return
        day.statements[msg.agent] = {
            "energy_charge": msg.energy_charge, "deviation_penalty": msg.deviation_penalty,
            "deviation_credit": msg.deviation_credit, "total": msg.total, "missing_subperiods": msg.missing_subperiods,
            "lines": [(line.deviation_penalty, line.deviation_credit, line.total) for line in msg.lines]}

    def _day_summary(self, day: Day, msg, at_ns: int) -> None:
        first = day.summary is None
        day.summary = {"agents": list(msg.agents), "rejected_messages": msg.rejected_messages,
                       "incidents": [i.model_dump() for i in msg.incidents]}
        if first:
            for incident in msg.incidents:
                self._incident(at_ns, incident.agent, incident.phase, incident.hour, incident.reason, "dmo")

    # --- helpers ----------------------------------------------------------------------------------------------------
    def _day(self, market_day: str) -> Day:
        """The day ``market_day`` is of; a new one ends the current day, whose statements become the bills so far."""
        if self.day is None:
            self.day = Day(market_day)
        elif self.day.market_day != market_day and market_day not in self.days_done:
            done = self.day
            for agent, totals in done.statements.items():
                before = self.settled_before.setdefault(agent, {k: 0.0 for k in MONEY})
                for k in MONEY:
                    before[k] += totals[k]
            self.days_done.append(done.market_day)
            self.day = Day(market_day)
        return self.day

    def _incident(self, at_ns: int, agent: str | None, phase: str, hour: int | None, reason: str,
                  source: str = "observed") -> None:
        self.incident_count += 1
        self.incidents.append({"at_ns": at_ns, "market_day": self.day.market_day if self.day else None,
                               "agent": agent, "phase": phase, "hour": hour, "reason": reason, "source": source})
        del self.incidents[:-KEPT_INCIDENTS]

    # --- what the DMO waits for -------------------------------------------------------------------------------------
    def waiting_for(self) -> list[str]:
        """The registered agents that have not yet answered the phase or hour the clock is in (a bid, a schedule, the
        hour's meter report), as the DMO waits for them on the logical clock; [] where it waits for none. A missing report
        the DMO settled without is the day summary's incident, not guessed here: a clock may overtake a report on the
        way to the observer."""
        if self.clock is None or self.day is None:
            return []
        phase, day = self.clock.phase, self.day
        if phase == "bidding":
            return [a for a in self.agents if a not in day.bids]
        if phase == "scheduling":
            return [a for a in self.agents if a not in day.schedules]
        if phase == "realtime" and self.clock.hour is not None:
            return [a for a in self.agents if self.clock.hour not in day.meter.get(a, {})]
        return []


MONEY = ("energy_charge", "deviation_penalty", "deviation_credit", "total")
