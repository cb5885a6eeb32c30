"""The fast tier's rule (README.md, "Tests"): a test not marked ``slow`` starts no process and opens no Zenoh session,
and fails, saying so, if it tries. A plugin of tests/conftest.py's; tests/project/test_tiers.py checks it.

The multi-process days, the Zenoh transport and whatever needs a fresh interpreter are what make the full suite take
minutes; ``-m "not slow"`` is the quick check while changing code, and it stays quick and honest only if nothing in
it quietly starts one. pytest-xdist's workers are started before any test runs, so they are never refused."""

from __future__ import annotations

import _posixsubprocess
import multiprocessing.process
import os
import platform
import signal
import subprocess
import threading
from contextlib import contextmanager

import pytest
import zenoh

# Every door to another process or to the network's bus: what ``-m "not slow"`` promises never to open, what
# opening it is called, and which positional argument names what it opened (None: none). Popen and Process.start
# come first; the rest catch whatever goes round them (a fork, a spawn, a forkserver's).
DOORS = ((subprocess.Popen, "__init__", "started a subprocess", 1),
         (_posixsubprocess, "fork_exec", "started a subprocess", 0),
         (multiprocessing.process.BaseProcess, "start", "started a multiprocessing process", 0),
         (os, "fork", "forked", None), (os, "forkpty", "forked", None), (os, "posix_spawn", "spawned a process", 1),
         (os, "posix_spawnp", "spawned a process", 1), (os, "system", "ran a shell command", 0),
         (zenoh, "open", "opened a Zenoh session", None))
# A fact about the machine that Python asks a subprocess for, once per process (``uname -p``), and that libraries ask
# for on their own (a Dask worker, to register): asked here, before any test, so that none starts that process.
platform.processor()

# How a refusal in another thread reaches the test's own (the main) thread, which may be waiting for that thread (a
# cluster for its worker, a launcher for its role) and would otherwise wait for ever: a signal whose handler fails
# the test. Once, and only while the test's own code runs (``_OWN_CODE``): raised in pytest's machinery, in the
# middle of its reporting, it broke the whole run. SIGURG, because nothing here uses it and one that comes after
# the test is ignored.
INTERRUPT = signal.SIGURG
_OWN_CODE: list[bool] = []  # not empty while a test function or a fixture's setup runs (the hooks at the end)


@contextmanager
def refusing_processes(test: str):
    """While ``test`` (a node id) runs, every door of ``DOORS`` raises ``pytest.fail`` instead of opening: a
    ``BaseException``, so that no ``except Exception`` of the code under test hides it. What was refused is also kept
    in the list this yields, so that a refusal in another thread, or one caught after all, still fails the test; the
    first in another thread also interrupts the main thread (``INTERRUPT``), so that the test fails rather than
    hangs."""
    refused: list[str] = []
    main = threading.main_thread()
    interrupting: list[bool] = []  # the main thread has been interrupted, or is about to be

    def refusal(what: str, shown: int | None):
        def refuse(*args, **kwargs):
            named = f" ({str(args[shown])[:200]})" if shown is not None and len(args) > shown else ""
            refused.append(f"{test} is not marked slow but {what}{named}: the fast tier, "
                           "-m 'not slow', starts no process and opens no Zenoh session. Run it in-process, or "
                           "mark it slow if it needs real processes (README.md, \"Tests\")")
            if threading.current_thread() is not main and not interrupting:
                interrupting.append(True)
                signal.pthread_kill(main.ident, INTERRUPT)
            pytest.fail(refused[-1])
        return refuse

    def interrupted(*_):
        if len(interrupting) == 1 and _OWN_CODE:
            interrupting.append(True)
            pytest.fail(refused[0])

    previous = signal.signal(INTERRUPT, interrupted)
    try:
        with pytest.MonkeyPatch.context() as patch:
            for owner, name, what, shown in DOORS:
                if hasattr(owner, name):
                    patch.setattr(owner, name, refusal(what, shown))
            yield refused
    finally:
        signal.signal(INTERRUPT, previous)


def _guarded(item):
    """The body of the three phase hooks below: a test marked slow runs as it is; any other under
    ``refusing_processes``, failed by the first refusal even if that was caught or raised in another thread."""
    if item.get_closest_marker("slow"):
        return (yield)
    with refusing_processes(item.nodeid) as refused:
        outcome = yield
    if refused:
        pytest.fail(refused[0], pytrace=False)
    return outcome


# Setup and teardown too: a fixture, of any scope, that starts a process does so for the test that first needs it.
@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item):
    return (yield from _guarded(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item):
    return (yield from _guarded(item))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item, nextitem):
    return (yield from _guarded(item))


def _own_code():
    _OWN_CODE.append(True)
    try:
        return (yield)
    finally:
        _OWN_CODE.pop()


@pytest.hookimpl(wrapper=True)
def pytest_pyfunc_call(pyfuncitem):
    return (yield from _own_code())


@pytest.hookimpl(wrapper=True)
def pytest_fixture_setup(fixturedef, request):
    return (yield from _own_code())
