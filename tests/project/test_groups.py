"""The tests that share a module fixture running a market day go to one pytest-xdist worker (tests/conftest.py,
``SHARED_DAYS``), so that the day runs once under the README's test command (``--dist loadgroup``), not once on each
worker; nothing else tells when the grouping silently stops taking effect (as it did with pytest 9.2, or with the
grouping hook running after pytest-xdist's)."""

import pytest


@pytest.fixture(scope="module")
def shared():
    """Stands for a market day that the tests of a module share."""
    return "day"


def test_the_tests_of_a_shared_day_are_one_group(request, shared):
    if not request.config.getoption("loadgroup", default=False):
        pytest.skip("only under --dist loadgroup (the README's test command)")
    assert request.node.nodeid.endswith("@test_groups-shared"), request.node.nodeid
