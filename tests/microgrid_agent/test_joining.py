"""An agent joins where the run is by asking the DMO for its clock until it answers
(microgrid_agent/agent/process.py, ``_join_where_the_run_is``), on a clock of the test's own."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from messages import Clock, Keys, encode, new_run_id
from microgrid_agent.agent import process
from microgrid_agent.agent.process import ANSWER_S, ASK_AFTER_S, ASK_AT_MOST_S, AgentTimeout, MicrogridAgent

TOKEN = "5" * 32  # the run's token, which the DMO's clock gives


class Dmo:
    """Answers the clock from the ``unanswered + 1``-th query on; before that each query times out (a DMO there but
    busy) or, with ``up=False``, finds nobody at once (a DMO not up yet)."""

    def __init__(self, now: list[float], unanswered: int, up: bool = True):
        self.keys, self.run_token = Keys(new_run_id()), ""
        self.now, self.unanswered, self.up = now, unanswered, up
        self.waited: list[float] = []  # how long each query waited for its answer

    def fetch(self, key: str, timeout_s: float):
        self.waited.append(timeout_s)
        if len(self.waited) <= self.unanswered:
            self.now[0] += timeout_s if self.up else 0.001
            return []
        clock = Clock(sender="dmo", run=TOKEN, market_day="2026-07-01", phase="registration", deadline_s=60.0,
                      day=1, days=3)
        return [(key, encode(clock), 0)]


def joined(monkeypatch, dmo: Dmo, idle_s: float = 600.0):
    now = dmo.now
    monkeypatch.setattr(process, "time", SimpleNamespace(monotonic=lambda: now[0],
                                                         sleep=lambda s: now.__setitem__(0, now[0] + s)))
    agent = SimpleNamespace(id="mg1", bus=dmo, config=SimpleNamespace(idle_s=idle_s), day=1)
    agent._latest = lambda keys, timeout_s=None: MicrogridAgent._latest(agent, keys, timeout_s)
    MicrogridAgent._join_where_the_run_is(agent)
    return agent


def test_a_busy_dmo_is_asked_less_often_the_longer_it_takes_to_answer(monkeypatch):
    """A thousand agents asking a busy DMO for its clock every two seconds kept it too busy to answer any: each
    unanswered query doubles the wait for the next answer, up to ASK_AT_MOST_S."""
    dmo = Dmo([0.0], unanswered=5)
    agent = joined(monkeypatch, dmo)
    assert dmo.waited == [ANSWER_S, 2 * ANSWER_S, ASK_AT_MOST_S, ASK_AT_MOST_S, ASK_AT_MOST_S, ASK_AT_MOST_S]
    assert (dmo.run_token, agent.days, agent.market_day) == (TOKEN, 3, "2026-07-01")


def test_a_dmo_not_up_yet_is_asked_again_soon_and_one_that_never_answers_ends_the_agent(monkeypatch):
    dmo = Dmo([0.0], unanswered=5, up=False)
    joined(monkeypatch, dmo)
    assert dmo.waited == [ANSWER_S] * 6  # nobody there: nothing to wait longer for
    assert dmo.now[0] == pytest.approx(5 * (0.001 + ASK_AFTER_S / 4))
    with pytest.raises(AgentTimeout, match="the DMO did not answer for 30 s"):
        joined(monkeypatch, Dmo([0.0], unanswered=10**6), idle_s=30.0)


@pytest.mark.parametrize("phase", ["registration", "bidding"])
def test_an_agent_that_hears_nothing_asks_for_the_clock_and_only_after_registration_for_the_rest(phase):
    """While the DMO's clock says registration it has sent nothing else: an agent asks it for the clock alone
    (a thousand registering agents asking for five keys each kept it too busy to answer)."""
    keys, asked = Keys(new_run_id()), []
    clock = Clock(sender="dmo", run=TOKEN, market_day="2026-07-01", phase=phase, deadline_s=60.0, day=1, days=1)

    def fetch(key, timeout_s):
        asked.append(key)
        return [(key, encode(clock), 0)] if key == keys.clock() else []

    events = []
    agent = SimpleNamespace(id="mg1", bus=SimpleNamespace(keys=keys, fetch=fetch, run_token=TOKEN), _bid_sent=False,
                            award=None, operator=None, statement=None, summary=None, market_day="2026-07-01", asked=0,
                            events=SimpleNamespace(put=events.append))
    agent._latest = lambda keys, timeout_s=None: MicrogridAgent._latest(agent, keys, timeout_s)
    MicrogridAgent._ask_the_dmo(agent)
    assert [e.kind for e in events] == ["clock"] and agent.asked == 1
    expected = [keys.clock()] + ([] if phase == "registration" else [
        keys.call_for_bids(), keys.award("mg1"), keys.statement("mg1"), keys.summary()])
    assert asked == expected
