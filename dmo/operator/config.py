"""What the DMO needs to run its days: their terms, deadlines and where it journals; and each day's islanding."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from messages.budget import BUDGET_BYTES, BUDGET_MESSAGES
from messages.schemas import PRICE_CAP, PRICE_FLOOR
from scenarios.days import day_seed, market_days
from scenarios.horizon import HOURS
from scenarios.network import Network

from ..market.choice import ChosenRule, paper_rule
from ..market.clearing import FLAT, IsoCurve


LOGICAL, WALL = "logical", "wall"
CLOCKS = (LOGICAL, WALL)  # how a phase ends: when every live agent has answered, or at the latest at its deadline


@dataclass(frozen=True)
class DayConfig:
    """Everything the DMO needs to run ``days`` consecutive market days from ``market_day``. On the ``logical`` clock a
    phase (an hour in real time) ends when every live agent has answered, however long that takes, and the deadlines
    are only what the clock messages announce; on the ``wall`` clock a phase ends at the latest when its deadline,
    wall-clock seconds, passes (docs/experiments.md, "Logical and wall-clock time"). What an experiment sets has no
    default here: its defaults are the experiment's (dmosim/experiment/spec.py). ``settlement`` is the rule, checked
    (``market.choice``). ``fixed_awards`` (24 MW) replaces clearing by those awards for every agent (the paper's
    Table I). ``islanded_hours`` holds for every day unless ``islanding_by_day`` gives each day its own."""

    market_day: str
    agents: int
    iso_price: tuple[float, ...]
    import_limit: float
    export_limit: float
    penalty: float
    subperiods: int
    islanded_hours: tuple[int, ...]
    credit: float
    registration_s: float
    bids_s: float
    schedule_s: float
    hour_s: float
    fixed_awards: tuple[float, ...] | None = None
    price_floor: float = PRICE_FLOOR
    price_cap: float = PRICE_CAP
    # After the last summary, how long at most to wait for the agents to leave before closing (None: as long as an
    # hour's reports get, hour_s: a thousand agents' last realised days come in tens of seconds on 2 cores)
    linger_s: float | None = None
    journal: str | None = None  # where the DMO journals its day, to resume it if it is restarted
    resume_wait_s: float = 30.0  # a resumed DMO waits this long for its agents to reconnect
    days: int = 1
    islanding_by_day: tuple[tuple[int, ...], ...] | None = None
    settlement: ChosenRule | None = None  # the settlement rule (None: the paper's at penalty and credit)
    network: Network | None = None  # the feeder the market clears on (None: the copper plate)
    placement: Mapping[str, str] = field(default_factory=dict)  # agent -> its bus on the feeder
    voltage_margin: float = 0.0  # p.u. the clearing keeps inside every bus's voltage limits (docs/network.md)
    clearing: str = "ac"  # on a feeder, one of distflow.CLEARING_METHODS (docs/market.md, "AC-faithful clearing")
    spill_price: float = 0.0  # $/MWh a feeder's spilled fixed generation costs the welfare (docs/market.md)
    iso_curve: IsoCurve = FLAT  # the ISO's blocks around its price at the substation (docs/market.md)
    budget: tuple[int, int] = (BUDGET_MESSAGES, BUDGET_BYTES)  # what one agent may send in a phase or hour
    # agents the run restarts (its restart faults): one that vanishes is waited for until a new process of it is
    # back, at most registration_s, as a new agent is at registration
    restarting: frozenset[str] = frozenset()
    clock: str = WALL  # one of CLOCKS; the experiment's default is the logical clock

    @property
    def logical(self) -> bool:
        """Whether phases end when every live agent has answered (the logical clock), never by seconds."""
        return self.clock == LOGICAL

    def __post_init__(self):
        if self.clock not in CLOCKS:
            raise ValueError(f"the clock is one of {', '.join(CLOCKS)}, not {self.clock!r}")
        if self.days < 1:
            raise ValueError(f"a run has at least one day, not {self.days}")
        if self.islanding_by_day is not None and len(self.islanding_by_day) != self.days:
            raise ValueError(f"islanding_by_day gives {len(self.islanding_by_day)} days, the run has {self.days}")
        self.iso_curve.check_prices(self.iso_price, self.price_floor, self.price_cap)

    @property
    def rule(self) -> ChosenRule:
        """The settlement rule the days are settled by (docs/settlement.md)."""
        return self.settlement or paper_rule(self.penalty, self.credit)

    @property
    def rates(self) -> tuple[float, float]:
        """The penalty and credit rates the DMO's messages announce: the paper rule's own, or under another rule
        the paper's term an agent that cannot read the rule schedules against."""
        rule = self.rule
        return (rule.parameters["penalty"], rule.parameters["credit"]) if rule.name == "paper" else (
            self.penalty, self.credit)

    def market_day_of(self, day: int) -> str:
        """The date of day ``day`` (1-based) of the run."""
        return market_days(self.market_day, day)[-1]

    def islanded(self, day: int) -> tuple[int, ...]:
        """The hours day ``day`` is islanded in."""
        return self.islanded_hours if self.islanding_by_day is None else self.islanding_by_day[day - 1]


def island_hours(start: int, hours: int) -> tuple[int, ...]:
    """The hours start..start+hours-1 of one islanding event (none if ``hours`` is 0)."""
    return tuple(range(start, start + hours)) if hours else ()


def draw_islanding(hours: int, seed: int) -> tuple[int, ...]:
    """One islanding event of ``hours`` whole hours at a seeded uniform start, as the scenarios draw them."""
    if not hours:
        return ()
    start = 1 + int(np.random.default_rng([seed, 7]).integers(0, HOURS + 1 - hours))
    return island_hours(start, hours)


def islanding_by_day(hours: int, seed: int, days: int) -> tuple[tuple[int, ...], ...]:
    """Each day's islanding event, drawn from that day's seed (``scenarios.days.day_seed``)."""
    return tuple(draw_islanding(hours, day_seed(seed, d)) for d in range(1, days + 1))
