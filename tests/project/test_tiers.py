"""The fast tier's rule holds (tests/fast_tier.py): a test not marked ``slow`` that starts a process or opens a Zenoh
session fails, saying why, however it tries and even if the refusal is caught or raised in another thread; a test
marked ``slow`` finds every door as it was. Checked on tests of its own, run in this process by pytester: each
refused before anything starts, so this check itself starts nothing."""

from __future__ import annotations

RULE = 'pytest_plugins = ("fast_tier",)\n'

TESTS = '''
import multiprocessing.process, os, subprocess, threading

import pytest
import zenoh

# The doors as they stand before any test of this file runs (whatever guards the run of this file itself).
DOORS = (subprocess.Popen.__init__, multiprocessing.process.BaseProcess.start, os.fork, zenoh.open)


def test_runs_a_command():
    subprocess.run(["true"], check=True)


def test_starts_a_process_of_its_own():
    multiprocessing.get_context("spawn").Process(target=print).start()


def test_forks():
    if os.fork() == 0:  # never reached: refused before the fork
        os._exit(0)


def test_opens_a_zenoh_session():
    zenoh.open(zenoh.Config())


def quietly(call, *args):
    """As a library's thread may: whatever goes wrong is dropped."""
    try:
        call(*args)
    except BaseException:
        pass


def test_hides_the_refusal_in_a_thread():
    thread = threading.Thread(target=quietly, args=(subprocess.run, ["true"]))
    thread.start()
    thread.join()


def test_waits_for_a_thread_that_was_refused():
    started = threading.Event()  # what the thread would set once its process runs
    threading.Thread(target=quietly, args=(subprocess.run, ["true"])).start()
    assert started.wait(60)  # interrupted at once, not after 60 s


def test_starts_nothing():
    now = (subprocess.Popen.__init__, multiprocessing.process.BaseProcess.start, os.fork, zenoh.open)
    assert all(door is not before for door, before in zip(now, DOORS))  # guarded, and passes all the same


@pytest.mark.slow
def test_marked_slow():
    assert (subprocess.Popen.__init__, multiprocessing.process.BaseProcess.start, os.fork, zenoh.open) == DOORS
'''


def test_a_test_not_marked_slow_fails_on_a_process_or_a_session_and_one_marked_slow_does_not(pytester):
    pytester.makeconftest(RULE)
    pytester.makeini("[pytest]\nmarkers = slow: real processes")
    pytester.makepyfile(test_rule=TESTS)
    run = pytester.inline_run("-q", "-p", "no:cacheprovider")
    passed, _, failed = run.listoutcomes()
    assert sorted(r.nodeid.split("::")[1] for r in passed) == ["test_marked_slow", "test_starts_nothing"]
    why = {r.nodeid.split("::")[1]: r.longreprtext for r in failed}
    for test, what in (("test_runs_a_command", "started a subprocess (['true'])"),
                       ("test_starts_a_process_of_its_own", "started a multiprocessing process"),
                       ("test_forks", "forked"), ("test_opens_a_zenoh_session", "opened a Zenoh session"),
                       ("test_hides_the_refusal_in_a_thread", "started a subprocess (['true'])"),
                       ("test_waits_for_a_thread_that_was_refused", "started a subprocess (['true'])")):
        assert f"test_rule.py::{test} is not marked slow but {what}" in why.pop(test)
    assert not why
