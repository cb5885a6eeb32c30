"""When an agent sends a payload again for want of its receipt (microgrid_agent/agent/delivery.py, ``Resends``): a
pure policy given the time, so it is checked here on a clock of the test's own, with no thread and no network."""

from __future__ import annotations

from messages import sha256
from microgrid_agent.agent.delivery import Resends, Silence


def test_a_payload_goes_again_at_doubling_intervals_up_to_the_cap_until_its_receipt_comes():
    r = Resends(first_s=0.5, max_s=4.0)
    r.sent("k/bid", b"bid", "bid", 3, now=10.0)
    times, now = [], 10.0
    while now < 30.0:
        now = r.next_due()
        times.append(now - 10.0)
        assert [p.seq for p in r.due(now)] == [3]
    assert times[:6] == [0.5, 1.5, 3.5, 7.5, 11.5, 15.5]  # waits 0.5, 1, 2, 4, 4, 4: doubling up to the cap
    assert r.receipt(sha256(b"bid")).kind == "bid"
    assert r.next_due() is None and r.due(now + 100) == []


def test_nothing_is_due_early_and_a_receipt_of_another_payload_changes_nothing():
    r = Resends(first_s=1.0, max_s=8.0)
    r.sent("k/meter", b"hour 1", "meter_report", 5, now=0.0)
    r.sent("k/meter", b"hour 2", "meter_report", 6, now=0.5)
    assert r.due(0.99) == []
    assert [p.seq for p in r.due(1.0)] == [5]
    assert r.receipt(sha256(b"a copy someone else sent")) is None
    assert [p.seq for p in r.due(1.5)] == [6]
    assert r.receipt(sha256(b"hour 1")).seq == 5 and set(r.pending) == {sha256(b"hour 2")}


def test_a_silent_agent_asks_again_at_doubling_intervals_and_gives_up_after_its_idle_time():
    silence = Silence(idle_s=20.0, since=100.0, first_s=1.0, max_s=8.0)
    now, asked_at = 100.0 + silence.wait, []
    while not silence.over(now):
        asked_at.append(now - 100.0)
        now += silence.asked(now)
    assert asked_at == [1.0, 3.0, 7.0, 15.0]  # waits 1, 2, 4, 8 (the cap) ...
    assert now == 120.0  # ... and then 5: the last wait ends when it gives up, never past it
