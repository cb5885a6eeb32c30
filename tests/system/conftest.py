"""Every test here starts real processes (a DMO, agents, a recorder, a router) and runs market days: the slow
part of the suite, left out by ``-m "not slow"`` (README.md)."""

import contextlib
import subprocess
import sys

import pytest


def pytest_collection_modifyitems(items):
    for item in items:
        if "tests/system/" in item.nodeid:
            item.add_marker(pytest.mark.slow)


@pytest.fixture
def busy_cores():
    """``with busy_cores():`` two busy loops, one per core of a 2-core machine, stopped on leaving."""
    @contextlib.contextmanager
    def loops(n: int = 2):
        running = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
        try:
            yield
        finally:
            for p in running:
                p.kill()
                p.wait()
    return loops
