"""The agents of one host take turns, as many at once as the machine has cores (microgrid_agent/agent/slots.py): a
turn is held while a message is handled, a turn given back goes to an agent waiting for any, and an agent killed
while holding one gives it back with its process."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from microgrid_agent.agent import slots


@pytest.fixture
def turns(monkeypatch):
    """A host's turns, as many as ``turns(n)`` says cores, removed after the test."""
    made = []

    def make(cores: int) -> None:
        monkeypatch.setattr(slots, "_semaphore", [])
        monkeypatch.setattr(os, "cpu_count", lambda: cores)
        slots.before_forks()
        made.extend(slots._semaphore)

    yield make
    for semaphore in made:
        slots._LIBC.semctl(semaphore, 0, 0)  # IPC_RMID, as the host's exit does


class Holder(threading.Thread):
    """An agent that takes a turn, says so, and keeps it until told to give it back."""

    def __init__(self, order: list[str], name: str):
        super().__init__(name=name)
        self.order, self.holding, self.release = order, threading.Event(), threading.Event()

    def run(self):
        with slots.computing():
            self.order.append(f"{self.name} in")
            self.holding.set()
            self.release.wait()
        self.order.append(f"{self.name} out")


def test_without_a_host_nothing_is_waited_for(monkeypatch):
    monkeypatch.setattr(slots, "_semaphore", [])
    with slots.computing(), slots.computing():  # both at once: no turn to take
        assert slots.free_turns() is None


@pytest.mark.parametrize("freed_first", [0, 1])
def test_a_turn_given_back_goes_to_the_agent_waiting_whichever_turn_it_is(turns, freed_first):
    """Two turns held, a third agent waiting: it gets in as soon as either is given back, the other still held."""
    turns(2)
    order = []
    holders = [Holder(order, "mg1"), Holder(order, "mg2")]
    for h in holders:
        h.start()
        h.holding.wait()
    assert slots.free_turns() == 0
    waiting = Holder(order, "mg3")
    waiting.start()
    holders[freed_first].release.set()
    assert waiting.holding.wait(timeout=60), order  # got a turn while the other holder keeps its own
    assert order[-1] == "mg3 in" and f"{holders[1 - freed_first].name} out" not in order
    for h in (*holders, waiting):
        h.release.set()
        h.join()
    assert slots.free_turns() == 2


def test_an_agent_killed_while_holding_its_turn_gives_it_back(turns):
    turns(1)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the agent: takes the turn, says so, and waits to be killed
        try:
            with slots.computing():
                os.write(write, b"x")
                signal.pause()
        finally:
            os._exit(1)
    os.close(write)
    assert os.read(read, 1) == b"x"
    assert slots.free_turns() == 0
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    os.close(read)
    assert slots.free_turns() == 1
