"""Bidding strategies (docs/strategies.md): the built-ins bid what their formulas say, the default bids exactly what
the price response gave, names are checked in one line, a user's class is made and tried, a strategy that fails
on a day costs its agent that day's bid only, and the name is swept, chosen per fleet member and registered."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from messages import BidStep, Registration, decode, encode
from messages.schemas import MAX_BID_STEPS, SCHEMA_VERSION, Award
from microgrid_agent.agent.bidding import bid_curve
from microgrid_agent.agent.machine import AgentConfig, AgentMachine, Solved
from microgrid_agent.agent.strategies import (NO_BID, DayLearned, Microgrid, StrategyError, checked_curve,
                                              choose_strategy, make_strategy, net_load, strategy_name, trial_call)
from scenarios.case import load_case
from scenarios.days import day_seed
from scenarios.horizon import HOURS

DAY = "2026-07-01"
# Table I of the paper (MW, hours 1..24), as /work's case notes transcribe it
TABLE_I = [0.70, 5.60, 4.90, 5.60, 6.30, 5.60, 4.90, 5.60, 6.30, 4.90, 5.60, 5.60, 6.30, 5.60, 6.30, 7.00, 8.40,
           9.80, 11.20, 10.50, 9.80, 7.70, 6.30, 5.60]


@pytest.fixture(scope="module")
def paper():
    return load_case("paper")



def agent_config(**given) -> AgentConfig:
    """A tiny agent's settings (an experiment's defaults live in dmosim, which the agent's tests do not import)."""
    settings = dict(scenarios=1, island_hours=1, gap=0.01, time_limit=60.0, seed=0, method="auto", workers=1,
                    load_scale=(), renewable_scale=())
    return AgentConfig(**(settings | given))

def microgrid(case, day=1, seed=0, gap=0.01) -> Microgrid:
    return Microgrid("mg1", case, day, DAY, day_seed(seed, day), gap)


def with_grid(case, **grid):
    return case.model_copy(update={"grid": case.grid.model_copy(update=grid)})


# --- the built-ins ------------------------------------------------------------------------------------------------

def test_table1_bids_the_table_i_award_at_the_price_cap(paper):
    call = trial_call(paper)
    curve = choose_strategy("table1", paper).bid(call, microgrid(paper))
    assert [len(hour) for hour in curve] == [1] * HOURS
    assert [hour[0].quantity_mw for hour in curve] == pytest.approx(TABLE_I, abs=1e-12)
    assert {hour[0].price_per_mwh for hour in curve} == {call.price_cap_per_mwh}
    half = choose_strategy("table1:scale=0.5", paper).bid(call, microgrid(paper))
    assert [hour[0].quantity_mw for hour in half] == pytest.approx([q / 2 for q in TABLE_I], abs=1e-12)


def test_table1_sells_an_export_award_at_the_floor_and_bids_nothing_for_zero(paper):
    award = [-2.0] * 12 + [0.0] * 12
    case = with_grid(paper, p_sch=award)
    call = trial_call(case)
    curve = choose_strategy("table1", case).bid(call, microgrid(case))
    assert curve[:12] == ((BidStep(price_per_mwh=call.price_floor_per_mwh, quantity_mw=-2.0),),) * 12
    assert curve[12:] == ((),) * 12


def test_naive_bids_the_forecast_net_load_at_the_iso_price(paper):
    call = trial_call(paper)
    curve = choose_strategy("naive", paper).bid(call, microgrid(paper))
    for t in range(HOURS):
        hour = t + 1
        net = paper.fixed_load.forecast[t] - sum(r.forecast[t] for r in paper.renewables)
        net += sum(d.energy / (d.beta - d.alpha + 1) for d in paper.loads if d.alpha <= hour <= d.beta)
        net = max(-paper.grid.p_m_max, min(paper.grid.p_m_max, net))
        (step,) = curve[t]
        assert step.price_per_mwh == call.iso_price_per_mwh[t] and step.quantity_mw == pytest.approx(net, abs=1e-12)
    small = with_grid(paper, p_m_max=1.0)  # the tie's limit (18) bounds it
    assert np.all(np.abs(net_load(small)) <= 1.0) and np.any(np.abs(net_load(paper)) > 1.0)


def test_the_default_strategy_bids_exactly_what_bid_curve_gave(paper):
    """The agent's bid under the default strategy, as it goes on the wire, is byte for byte the bid the agent sent
    before strategies: bid_curve at the call's ISO price, the day's seed and the agent's gap."""
    agent = AgentMachine("mg1", paper, agent_config(seed=7, gap=0.02), DAY)
    call = trial_call(paper).model_copy(update={"market_day": DAY})
    (send,) = agent.handle(call)
    sent = send.msg
    before = bid_curve(paper, np.asarray(call.iso_price_per_mwh), seed=day_seed(7, 1), gap=0.02)
    assert agent.strategy.label == "price-response"
    assert encode(sent) == encode(sent.model_copy(update={"hours": before}))
    assert sent.hours == before and sum(map(len, before)) > HOURS  # a curve of several steps, not a trivial one


# --- strategies of one's own, for the tests below (``tests.microgrid_agent.test_strategies:Class``) ---------------

class Flat:
    """Buys ``mw`` every hour at ``price``, and remembers each day's clearing prices."""

    def __init__(self, mw: float = 1.0, price: float = 50.0):
        self.mw, self.price, self.seen = mw, price, []

    def bids(self, call, microgrid):
        return [[BidStep(price_per_mwh=self.price, quantity_mw=self.mw)] for _ in range(HOURS)]

    def observe(self, result):
        self.seen.append(result.clearing_prices)


class Raises:
    def bids(self, call, microgrid):
        raise ZeroDivisionError("no\nsuch luck")


class TooShort:
    def bids(self, call, microgrid):
        return [()] * (HOURS - 1)


class Pairs:
    def bids(self, call, microgrid):
        return [[(50.0, 1.0)]] * HOURS


class NotFinite:
    def bids(self, call, microgrid):
        return [[BidStep.model_construct(price_per_mwh=float("nan"), quantity_mw=1.0)]] * HOURS


class Text:
    def bids(self, call, microgrid):
        return [[BidStep.model_construct(price_per_mwh="50", quantity_mw=1.0)]] * HOURS


class BadLength:
    class Hours:
        def __len__(self):
            raise RuntimeError("no length")

    def bids(self, call, microgrid):
        return self.Hours()


class TooManySteps:
    def bids(self, call, microgrid):
        return [[BidStep(price_per_mwh=float(k), quantity_mw=0.1) for k in range(MAX_BID_STEPS + 1)]] * HOURS


class NoBids:
    def bid(self, call, microgrid):  # not the method's name
        return NO_BID


class Picky:
    def __init__(self, level: float = 1.0):
        if level > 1:
            raise ValueError("level above 1")


HERE = "tests.microgrid_agent.test_strategies"


@pytest.mark.parametrize("spec, expected", [
    ("", "no strategy named"),
    ("nosuch", "unknown strategy 'nosuch': the built-in strategies are price-response, table1, naive"),
    ("table1:width=1", "strategy table1 has no parameter 'width' (its parameters: scale)"),
    ("table1:scale=20", "strategy table1: scale must be in [0, 10], got 20"),
    ("naive:scale=1", "strategy naive has no parameter 'scale' (its parameters: none)"),
    ("table1:scale=abc", "strategy table1: 'scale=abc' is not key=number"),
    ("table1:scale=inf", "strategy table1: 'scale=inf' is not key=number"),
    ("mine.py:not-a-class", "strategy mine.py:not-a-class: 'not-a-class' is not a class name"),
    ("bad module:C", "'bad module' is neither path/to/strategy.py nor a module name"),
    ("tests/no_such_file.py:C", "strategy tests/no_such_file.py:C: no file tests/no_such_file.py"),
    ("no_such_module_here:C", "cannot load no_such_module_here: ModuleNotFoundError"),
    (f"{HERE}:Nothing", f"{HERE} has no class 'Nothing'"),
    (f"{HERE}:NoBids", f"strategy {HERE}:NoBids: NoBids has no method bids(call, microgrid)"),
    (f"{HERE}:Flat:width=1", f"strategy {HERE}:Flat has no parameter 'width' (its parameters: mw, price)"),
    (f"{HERE}:Picky:level=2", f"strategy {HERE}:Picky:level=2: cannot be made: ValueError: level above 1"),
    (f"{HERE}:Raises", f"strategy {HERE}:Raises failed: ZeroDivisionError: no such luck"),
    (f"{HERE}:TooShort", "returned no bid: 23 hours of steps, not 24"),
    (f"{HERE}:Pairs", "returned no bid: hour 1, step 1: tuple, not a messages.BidStep"),
    (f"{HERE}:NotFinite", "returned no bid: hour 1, step 1: price and quantity must be finite numbers"),
    (f"{HERE}:Text", "returned no bid: hour 1, step 1: price and quantity must be finite numbers"),
    (f"{HERE}:BadLength", "returned no bid: no length"),
    (f"{HERE}:TooManySteps", f"returned no bid: hour 1: {MAX_BID_STEPS + 1} steps, at most {MAX_BID_STEPS}"),
])
def test_a_strategy_that_cannot_be_used_is_one_line_naming_it(paper, spec, expected):
    with pytest.raises(StrategyError) as err:
        choose_strategy(spec, paper)
    assert expected in str(err.value) and "\n" not in str(err.value)


def test_naming_a_strategy_imports_nothing_and_says_what_code_it_would_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine.py").write_text("raise SystemExit('imported')\n")
    name = strategy_name("mine.py:Mine:shade=0.5,memory=3")  # the file would exit if it were imported
    assert (name.target, dict(name.params), name.label) == ("mine.py:Mine", {"shade": 0.5, "memory": 3.0},
                                                            "mine.py:Mine:shade=0.5,memory=3")
    assert name.code == f"{tmp_path / 'mine.py'}:Mine" and strategy_name("table1").code is None


def test_a_user_strategy_from_a_file_is_made_with_its_parameters_and_starts_with_no_memory_of_its_trial(
        tmp_path, paper):
    (tmp_path / "flat.py").write_text(
        "from tests.microgrid_agent.test_strategies import Flat as Base\n\n"
        "class Flat(Base):\n    made = 0\n\n    def __init__(self, **params):\n        super().__init__(**params)\n"
        "        Flat.made += 1\n")
    chosen = choose_strategy(f"{tmp_path}/flat.py:Flat:mw=2.5", paper)
    assert chosen.label == f"{tmp_path}/flat.py:Flat:mw=2.5" and type(chosen.strategy).made == 2  # trial, then it
    curve = chosen.bid(trial_call(paper), microgrid(paper))
    assert curve == ((BidStep(price_per_mwh=50.0, quantity_mw=2.5),),) * HOURS and chosen.strategy.seen == []


def test_checked_curve_takes_any_sequences_of_bid_steps_as_tuples():
    step = BidStep(price_per_mwh=1.0, quantity_mw=-1.0)
    assert checked_curve([[step]] * HOURS) == ((step,),) * HOURS
    with pytest.raises(ValueError, match="expected 24 hours of steps, got dict"):
        checked_curve({})


# --- the agent with a strategy that fails on a day -----------------------------------------------------------------

def test_an_agent_whose_strategy_fails_bids_nothing_that_day_says_why_and_observes_on(paper, caplog):
    agent = AgentMachine("mg1", paper, agent_config(), DAY, make_strategy(strategy_name(f"{HERE}:Raises")))
    with caplog.at_level(logging.WARNING, "dmosim.agent"):
        (send,) = agent.handle(trial_call(paper).model_copy(update={"market_day": DAY}))
    sent = send.msg
    assert sent.hours == NO_BID and agent._bid_sent
    (said,) = caplog.records  # why, in one warning: which strategy, and what it raised
    assert said.levelname == "WARNING" and f"{HERE}:Raises" in said.getMessage()
    assert "ZeroDivisionError: no such luck" in said.getMessage()


def test_the_agent_tells_its_strategy_the_day_it_bid(paper):
    agent = AgentMachine("mg1", paper, agent_config(), DAY, make_strategy(strategy_name(f"{HERE}:Flat:mw=2")))
    agent.handle(trial_call(paper).model_copy(update={"market_day": DAY}))
    agent._observe()  # no award came: the strategy learns its bid and no prices
    assert agent.strategy.strategy.seen == [None]
    learned = DayLearned(1, DAY, NO_BID, None, None, None)
    assert learned.clearing_prices is None


# --- the name on the wire ------------------------------------------------------------------------------------------

def test_the_registration_carries_the_strategy_and_an_older_one_reads_as_naming_none():
    reg = Registration(sender="mg1", market_day=DAY, case="paper", max_import_mw=12.0, max_export_mw=12.0,
                       strategy="table1:scale=0.5")
    assert decode(encode(reg)).strategy == "table1:scale=0.5"
    older = encode(reg).replace(f'"schema_version":{SCHEMA_VERSION}'.encode(), b'"schema_version":5').replace(
        b',"strategy":"table1:scale=0.5"', b"").replace(b',"bus":null', b"")  # version 5 had neither
    assert b"strategy" not in older and decode(older).strategy is None



def test_each_days_schedule_starts_from_the_one_before(paper):
    """An agent's solve is handed the first stage of its previous schedule (none on its first day): the Benders
    route takes it as its first incumbent (microgrid_agent/solvers/benders.py, ``begin_from``)."""
    agent = AgentMachine("mg1", paper, agent_config(), DAY)
    starts, firsts = [], []
    for day in (1, 2):
        agent.day = day
        (solve,) = agent._schedule(Award(sender="dmo", market_day=DAY, agent="mg1", p_sch_mw=tuple(paper.grid.p_sch),
                                         clearing_price_per_mwh=(50.0,) * HOURS, penalty_per_mwh=150.0, subperiods=1,
                                         rules_version=1, rules="paper"))
        schedule = solve.job.run()
        agent.handle(Solved(schedule))
        starts.append(solve.job.start)
        firsts.append(schedule.first)
    assert starts[0] is None and starts[1] is firsts[0]
