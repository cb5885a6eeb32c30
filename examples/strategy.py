"""A bidding strategy of one's own (docs/strategies.md, "Writing a strategy"): the price response, with each step's
price pulled towards what the market cleared at on the days before.

    dmosim run --agents 2 --strategy examples/strategy.py:Shaded:shade=0.5,memory=3
    python examples/strategy.py [OUT]   # one tiny agent, two days, into OUT (default runs/<run_id>): the second
                                        # day's bid remembers the first day's prices

A strategy is a class with a method ``bids(call, microgrid)`` that returns 24 hours of ``BidStep``s; the agent makes
it once with the parameters of its name as keyword arguments, and calls ``observe(result)``, if it has one, at the
end of each day, so it may keep what it learns.
"""

from collections import deque

from messages import BidStep
from microgrid_agent.agent.strategies import DayLearned, Microgrid, RespondToPrice


class Shaded:
    """The price response (``price-response``), each step's price moved ``shade`` of the way from its own price to
    the mean clearing price of its hour over the last ``memory`` days; on the first day, the price response as is."""

    def __init__(self, shade: float = 0.5, memory: float = 3):
        if not 0 <= shade <= 1 or memory < 1:
            raise ValueError("shade is in [0, 1] and memory at least 1 day")
        self.shade = shade
        self.seen = deque(maxlen=int(memory))  # the clearing prices of the last days, 24 each
        self.respond = RespondToPrice()

    def bids(self, call, microgrid: Microgrid):
        curve = self.respond.bids(call, microgrid)
        if not self.seen:
            return curve
        mean = [sum(day[t] for day in self.seen) / len(self.seen) for t in range(24)]
        return tuple(tuple(BidStep(price_per_mwh=step.price_per_mwh + self.shade * (mean[t] - step.price_per_mwh),
                                   quantity_mw=step.quantity_mw) for step in hour)
                     for t, hour in enumerate(curve))

    def observe(self, result: DayLearned) -> None:
        if result.clearing_prices is not None:
            self.seen.append(result.clearing_prices)


if __name__ == "__main__":
    import sys
    from pathlib import Path

    from dmosim.experiment.spec import parse_experiment
    from dmosim.launch.local import run_experiment
    from messages.recording import read_recording

    experiment = parse_experiment({
        "name": "shaded", "days": 2, "market_day": "2026-07-06",
        "agents": {"count": 1, "strategy": f"{Path(__file__).resolve()}:Shaded:shade=0.5"},
        "market": {"subperiods": 1, "island_hours": 0}, "schedule": {"scenarios": 1, "gap": 0.05},
    })
    result = run_experiment(experiment, sys.argv[1] if len(sys.argv) > 1 else None)
    rec = read_recording(result.recording)
    for _, msg in rec.decoded("registration"):
        print(f"{msg.sender} registered, bidding with {msg.strategy}")
    for _, msg in rec.decoded("bid"):
        prices = sorted({step.price_per_mwh for hour in msg.hours for step in hour})
        print(f"{msg.market_day}: {msg.sender} bid {sum(map(len, msg.hours))} steps at "
              f"{prices[0]:.2f}..{prices[-1]:.2f} $/MWh")
    print(f"run {result.run_id}: {result.run_dir}")
