"""What the DMO's machine publishes and settles by: the market it runs. The machine sequences the day and decides on
what agents send (machine.py); a market says who may register, what the call for bids, the awards and each hour's
grid state are, and how the day settles. ``LiveMarket`` clears the bids the day accepted (on the copper plate or a
feeder); a recorded day is another (dmo/replay/recorded.py), which ``dmosim replay --as-dmo`` runs.
"""

from __future__ import annotations

from typing import Protocol

from messages import Award, CallForBids, GridState, Message, SettlementStatement
from scenarios.horizon import HOURS

from ..market.clearing import BidCurve, ClearingResult, Step, clear, fixed_awards
from ..market.distflow import NetworkClearing, clear_network
from ..market.settlement import DayTotals, Statement, accepted_day
from . import feeder, intake, outbox
from .config import DayConfig
from .intake import Accept
from .state import DayState

Clearing = ClearingResult | NetworkClearing


class DayMarket(Protocol):
    """The terms, the clearing and the settlement of the days the machine runs."""

    def registration(self, state: DayState) -> Accept:
        """The rule of the registration phase."""

    def call_for_bids(self, day: int, deadline_s: float) -> CallForBids:
        """Day ``day``'s terms; bids due ``deadline_s`` after it is sent."""

    def clear(self, state: DayState) -> Clearing:
        """The day's clearing, a pure function of what the day accepted (a resumed DMO gets the same again)."""

    def award(self, state: DayState, clearing: Clearing, agent: str) -> Award:
        """One agent's award."""

    def planned(self, state: DayState, clearing: Clearing) -> list[Message]:
        """What else goes out with the awards (on a feeder, each hour as planned)."""

    def grid_states(self, state: DayState, clearing: Clearing) -> list[GridState]:
        """Each hour's grid state, hours 1..24."""

    def settle(self, state: DayState, clearing: Clearing) -> tuple[dict[str, Statement], DayTotals]:
        """The day's statements and totals, from its awards and the meter reports it accepted."""

    def statement(self, state: DayState, st: Statement) -> SettlementStatement:
        """A statement as the message the DMO publishes."""

    def realised(self, state: DayState) -> list[Message]:
        """What goes out with the statements (on a feeder, each hour as realised)."""


def bid_curve(bid) -> BidCurve:
    """A received bid as the clearing reads it (hours 0..23)."""
    return BidCurve(bid.sender, tuple(tuple(Step(st.price_per_mwh, st.quantity_mw) for st in hour)
                                      for hour in bid.hours))


class LiveMarket:
    """The market of ``config``: the bids the day accepted cleared on the copper plate, or on the feeder with each
    agent at its bus (or the given awards of ``fixed_awards``), and settled by the configured rule."""

    def __init__(self, config: DayConfig):
        self.config = config

    def registration(self, state: DayState) -> Accept:
        return intake.registration(state, self.config.network, self.config.placement)

    def call_for_bids(self, day: int, deadline_s: float) -> CallForBids:
        return outbox.call_for_bids(self.config, day, deadline_s)

    def clear(self, state: DayState) -> Clearing:
        c, agents = self.config, sorted(state.registered)
        if c.fixed_awards is not None:
            return fixed_awards({a: c.fixed_awards for a in agents}, c.iso_price)
        bids = [bid_curve(state.bids[a]) for a in sorted(state.bids)]
        if c.network is not None:
            return clear_network(bids, c.network, feeder.sites(c, state), c.iso_price, c.import_limit,
                                 c.export_limit, agents=agents, margin=c.voltage_margin, curve=c.iso_curve,
                                 method=c.clearing, spill_price=c.spill_price)
        return clear(bids, c.iso_price, c.import_limit, c.export_limit, agents=agents, curve=c.iso_curve)

    def award(self, state: DayState, clearing: Clearing, agent: str) -> Award:
        return outbox.award(self.config, state.day, clearing, agent, feeder.sites(self.config, state).get(agent))

    def planned(self, state: DayState, clearing: Clearing) -> list[Message]:
        if not isinstance(clearing, NetworkClearing):
            return []
        return feeder.planned(self.config, state.day, clearing, feeder.sites(self.config, state))

    def grid_states(self, state: DayState, clearing: Clearing) -> list[GridState]:
        c = self.config
        rooms = None  # on a feeder, the day's operating envelope, from its clearing
        if isinstance(clearing, NetworkClearing):
            rooms = feeder.envelope(c, clearing, feeder.sites(c, state))
        return [outbox.grid_state(c, state.day, hour, rooms) for hour in range(1, HOURS + 1)]

    def settle(self, state: DayState, clearing: Clearing) -> tuple[dict[str, Statement], DayTotals]:
        """On a feeder each agent's energy at its own bus's prices; the rule sees the day's grid states as they were
        published (``grid_states``, a pure function of the day and its clearing)."""
        own = dict(clearing.agent_price) if isinstance(clearing, NetworkClearing) else None
        return self.config.rule.settle(accepted_day(clearing.awards, clearing.price, state.meter,
                                                    subperiods=self.config.subperiods, registered=state.registered,
                                                    agent_prices=own, grid=self.grid_states(state, clearing),
                                                    bus=feeder.sites(self.config, state)))

    def statement(self, state: DayState, st: Statement) -> SettlementStatement:
        c = self.config
        return outbox.statement_message(st, state.market_day, *c.rates, c.rule.label)

    def realised(self, state: DayState) -> list[Message]:
        c = self.config
        return [] if c.network is None else feeder.realised(c, state.day, state, feeder.sites(c, state))
