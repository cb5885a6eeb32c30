"""The agents of one host take turns, as many at once as the machine has cores (microgrid_agent/agent/slots.py): a
turn is held while a message is handled, a turn given back goes to an agent waiting for any, a process holds one turn
at a time, and an agent killed while holding one gives it back with its process."""

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


class Agent:
    """An agent in a forked process of its own: takes a turn, says so on a pipe, and keeps it until told to give it
    back (or is killed)."""

    def __init__(self):
        self._said, said = os.pipe()
        release, self._release = os.pipe()
        self.pid = os.fork()
        if self.pid == 0:
            try:
                with slots.computing():
                    os.write(said, b"x")
                    os.read(release, 1)
            finally:
                os._exit(0)
        os.close(said)
        os.close(release)

    def holding(self) -> bool:
        """Waits until it holds its turn (it says so once it does)."""
        return os.read(self._said, 1) == b"x"

    def give_back(self) -> None:
        os.write(self._release, b"x")
        os.waitpid(self.pid, 0)

    def kill(self) -> None:
        os.kill(self.pid, signal.SIGKILL)
        os.waitpid(self.pid, 0)


def test_without_a_host_nothing_is_waited_for(monkeypatch):
    monkeypatch.setattr(slots, "_semaphore", [])
    with slots.computing(), slots.computing():  # both at once: no turn to take
        assert slots.free_turns() is None


@pytest.mark.parametrize("freed_first", [0, 1])
@pytest.mark.slow  # the turns are shared by processes: the agents are forked
def test_a_turn_given_back_goes_to_the_agent_waiting_whichever_turn_it_is(turns, freed_first):
    """Two turns held, a third agent waiting: it gets in as soon as either is given back, the other still held."""
    turns(2)
    holders = [Agent(), Agent()]
    assert all(h.holding() for h in holders) and slots.free_turns() == 0
    waiting = Agent()
    holders[freed_first].give_back()
    assert waiting.holding() and slots.free_turns() == 0  # the other holder keeps its own
    holders[1 - freed_first].give_back()
    waiting.give_back()
    assert slots.free_turns() == 2


@pytest.mark.slow
def test_a_process_holds_one_turn_at_a_time(turns):
    """Two agents of one process: the second waits for the first although a turn is free, then gets one."""
    turns(2)
    order, first_in, release = [], threading.Event(), threading.Event()

    def first():
        with slots.computing():
            order.append("mg1 in")
            first_in.set()
            release.wait()
            order.append("mg1 out")

    def second():
        with slots.computing():
            order.append("mg2 in")

    threads = [threading.Thread(target=first), threading.Thread(target=second)]
    threads[0].start()
    try:
        first_in.wait()
        threads[1].start()
        other = Agent()  # another process takes the turn the second agent could not
        assert other.holding() and slots.free_turns() == 0
        other.give_back()
    finally:  # a failure above must not leave the first agent holding its turn, and this process, for ever
        release.set()
        for t in threads:
            if t.ident is not None:  # started
                t.join()
    assert order == ["mg1 in", "mg1 out", "mg2 in"] and slots.free_turns() == 2


@pytest.mark.slow
def test_an_agent_killed_while_holding_its_turn_gives_it_back(turns):
    turns(1)
    agent = Agent()
    assert agent.holding() and slots.free_turns() == 0
    agent.kill()
    assert slots.free_turns() == 1
