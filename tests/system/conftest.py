"""Every test here starts real processes (a DMO, agents, a recorder, a router) and runs market days: the slow
part of the suite, left out by ``-m "not slow"`` (README.md)."""

import pytest


def pytest_collection_modifyitems(items):
    for item in items:
        if "tests/system/" in item.nodeid:
            item.add_marker(pytest.mark.slow)
