"""The agents of one host take turns in as many slots as the machine has cores (microgrid_agent/agent/slots.py): a
slot is held while a message is handled, the next agent gets it once it is given back, and an agent killed while
holding one gives it back with its process."""

from __future__ import annotations

import fcntl
import os
import signal
import threading

import pytest

from microgrid_agent.agent import slots


def free(path: str) -> bool:
    fd = os.open(path, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    finally:
        os.close(fd)


@pytest.fixture
def one_slot(monkeypatch) -> str:
    monkeypatch.setattr(slots, "_paths", [])
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    slots.before_forks()
    (path,) = slots._paths
    return path


def test_without_a_host_nothing_is_waited_for(monkeypatch):
    monkeypatch.setattr(slots, "_paths", [])
    with slots.computing("mg1"), slots.computing("mg2"):  # both at once: no slot to take
        pass


def test_an_agent_waits_while_another_holds_the_slot_and_gets_it_once_given_back(one_slot):
    holding, release, order = threading.Event(), threading.Event(), []

    def first():
        with slots.computing("mg1"):
            holding.set()
            release.wait()
            order.append("mg1 done")

    def second():
        with slots.computing("mg2"):
            order.append("mg2 in")

    threads = [threading.Thread(target=first)]
    threads[0].start()
    holding.wait()
    assert not free(one_slot)
    threads.append(threading.Thread(target=second))
    threads[1].start()
    release.set()
    for t in threads:
        t.join()
    assert order == ["mg1 done", "mg2 in"] and free(one_slot)


def test_an_agent_killed_while_holding_its_slot_gives_it_back(one_slot):
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the agent: takes the slot, says so, and waits to be killed
        try:
            with slots.computing("mg1"):
                os.write(write, b"x")
                signal.pause()
        finally:
            os._exit(1)
    os.close(write)
    assert os.read(read, 1) == b"x"
    assert not free(one_slot)
    os.kill(pid, signal.SIGKILL)
    os.waitpid(pid, 0)
    os.close(read)
    assert free(one_slot)
