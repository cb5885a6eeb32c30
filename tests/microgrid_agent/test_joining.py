"""An agent joins where the run is by asking the DMO for its clock until it answers (microgrid_agent/agent/delivery.py,
``Joining``: a pure policy, on a clock of the test's own), and a silent agent asks the DMO for what its machine
waits for (microgrid_agent/agent/machine.py, ``waiting_for`` and ``wants``)."""

from __future__ import annotations

import pytest

from messages import CallForBids, Clock
from microgrid_agent.agent.delivery import Joining
from microgrid_agent.agent.machine import AgentConfig, AgentMachine
from microgrid_agent.agent.process import ANSWER_S, ASK_AFTER_S, ASK_AT_MOST_S
from microgrid_agent.agent.strategies import make_strategy, strategy_name
from scenarios.case import load_case

TOKEN = "5" * 32  # the run's token, which the DMO's clock gives
DAY = "2026-07-01"
CONFIG = AgentConfig(scenarios=1, island_hours=0, gap=0.01, time_limit=None, seed=0, method="auto", workers=1,
                     load_scale=(), renewable_scale=())


def joining(idle_s: float = 600.0) -> Joining:
    return Joining(idle_s, 0.0, ANSWER_S, ASK_AT_MOST_S, ASK_AFTER_S / 4)


def asked_unanswered(policy: Joining, queries: int, took: float | None = None) -> tuple[list[float], float]:
    """How long each of ``queries`` unanswered queries waited for its answer, and when the next one goes: each took
    its whole wait (a DMO there but busy), or ``took`` (a DMO not up yet answers nothing at once)."""
    now, waited = 0.0, []
    for _ in range(queries):
        waited.append(policy.wait)
        asked, now = now, now + (policy.wait if took is None else took)
        now += policy.unanswered(asked, now)
    return waited + [policy.wait], now


def test_a_busy_dmo_is_asked_less_often_the_longer_it_takes_to_answer():
    """A thousand agents asking a busy DMO for its clock every two seconds kept it too busy to answer any: each
    unanswered query doubles the wait for the next answer, up to ASK_AT_MOST_S."""
    waited, _ = asked_unanswered(joining(), 5)
    assert waited == [ANSWER_S, 2 * ANSWER_S, ASK_AT_MOST_S, ASK_AT_MOST_S, ASK_AT_MOST_S, ASK_AT_MOST_S]


def test_a_dmo_not_up_yet_is_asked_again_soon_and_one_that_never_answers_ends_the_agent():
    waited, now = asked_unanswered(joining(), 5, took=0.001)
    assert waited == [ANSWER_S] * 6  # nobody there: nothing to wait longer for
    assert now == pytest.approx(5 * (0.001 + ASK_AFTER_S / 4))
    policy = joining(idle_s=30.0)
    assert policy.unanswered(asked=29.8, now=29.9) == ASK_AFTER_S / 4
    assert policy.unanswered(asked=29.95, now=30.0) is None  # 30 s after it began: it gives up


def test_the_clock_tells_the_machine_the_runs_token_and_where_the_run_is():
    machine = AgentMachine("mg1", load_case("paper"), CONFIG, "2026-06-01")
    machine.join(Clock(sender="dmo", run=TOKEN, market_day=DAY, phase="bidding", deadline_s=60.0, day=2, days=3))
    assert (machine.run_token, machine.market_day, machine.day, machine.days) == (TOKEN, DAY, 2, 3)


@pytest.mark.parametrize("phase", ["registration", "bidding"])
def test_an_agent_that_hears_nothing_asks_for_the_clock_and_only_after_registration_for_the_rest(phase):
    """While the DMO's clock says registration it has sent nothing else: an agent asks it for the clock alone
    (a thousand registering agents asking for five keys each kept it too busy to answer)."""
    machine = AgentMachine("mg1", load_case("paper"), CONFIG, DAY)
    expected = [] if phase == "registration" else ["call_for_bids", "award", "settlement_statement", "day_summary"]
    assert machine.waiting_for(phase == "registration") == expected


def test_an_answer_is_handled_only_if_it_tells_the_agent_something_new():
    paper = load_case("paper")
    machine = AgentMachine("mg1", paper, CONFIG, DAY, make_strategy(strategy_name("table1")))  # bids at once
    call = CallForBids(sender="dmo", market_day=DAY, iso_price_per_mwh=tuple(paper.grid.iso_price),
                       price_floor_per_mwh=-100.0, price_cap_per_mwh=1000.0, import_limit_mw=8.0, export_limit_mw=8.0,
                       penalty_per_mwh=150.0, subperiods=1, deadline_s=60.0)
    clock = Clock(sender="dmo", market_day="2026-07-02", phase="bidding", deadline_s=60.0, day=2, days=2)
    assert machine.wants(call) and machine.wants(clock)  # a clock of any day: where the run is
    assert not machine.wants(call.model_copy(update={"market_day": "2026-06-30"}))  # another day's
    machine.handle(call)  # its bid goes
    assert not machine.wants(call) and machine.waiting_for(False)[0] == "award"
