"""The budget one sender has in a window (messages/budget.py): so many messages and bytes, then nothing until the
next window, each sender on its own."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from messages.budget import SenderBudget
from messages.keys import agent_of


@given(sizes=st.lists(st.integers(0, 100), max_size=40), messages=st.integers(1, 10), size=st.integers(0, 500))
def test_a_sender_gets_what_fits_in_order_and_nothing_after_the_first_that_does_not(sizes, messages, size):
    budget = SenderBudget(messages, size)
    admitted = [budget.admit("mg1", n) == 0 for n in sizes]
    fits = [i < messages and sum(sizes[:i + 1]) <= size for i in range(len(sizes))]
    first_over = fits.index(False) if False in fits else len(sizes)
    assert admitted[:first_over] == [True] * first_over  # everything up to the first that does not fit
    assert sum(admitted) <= messages and sum(n for n, ok in zip(sizes, admitted) if ok) <= size
    assert budget.dropped["mg1"] == admitted.count(False)


def test_each_sender_has_its_own_budget_and_a_new_window_starts_every_one_afresh():
    budget = SenderBudget(2, 1000)
    assert [budget.admit("mg1", 10) for _ in range(4)] == [0, 0, 1, 2]  # the first over says it is the first
    assert budget.admit("mg2", 10) == 0 and budget.admit(None, 10) == 0  # mg1's flood costs no one else
    assert budget.admit("mg1", 0) == 3
    assert budget.next_window() == {"mg1": 3}
    assert budget.admit("mg1", 1000) == 0 and budget.admit("mg1", 1) == 1  # a new window, its bytes spent at once
    assert budget.next_window() == {"mg1": 1} and budget.next_window() == {}


def test_only_an_agents_own_keys_name_a_sender():
    assert agent_of("dmosim/r1/agent/mg1/meter") == "mg1"
    assert agent_of("dmosim/r1/agent/mg1/anything/else") == "mg1"
    for key in ("dmosim/r1/dmo/award/mg1", "dmosim/r1/agent/dmo/bid", "dmosim/r1/agent/1x/meter", "dmosim/r1/agent",
                "", "dmosim/r1/agent/" + "m" * 300 + "/bid"):
        assert agent_of(key) is None, key
