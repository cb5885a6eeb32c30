"""A bidding strategy for tests: the price response, and at the end of each day what the agent learned written as
one JSON line to ``$DMOSIM_TEST_OBSERVED/<agent>.jsonl`` (the day, and the total of its statement: None if it ended
without one). What an agent learned is then read from a file it wrote, not from its log."""

import json
import os
from pathlib import Path

from microgrid_agent.agent.strategies import DayLearned, RespondToPrice


class Observing(RespondToPrice):
    def observe(self, result: DayLearned) -> None:
        agent = result.statement.agent if result.statement is not None else result.award.agent
        line = {"market_day": result.market_day,
                "statement_total": None if result.statement is None else result.statement.total}
        with open(Path(os.environ["DMOSIM_TEST_OBSERVED"]) / f"{agent}.jsonl", "a") as f:
            f.write(json.dumps(line) + "\n")
