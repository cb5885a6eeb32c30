"""What tests of several packages share: waiting for a process that is not the test's own child to end."""

from __future__ import annotations

import os
import select

import pytest


def _gone(pid: int, timeout_s: float = 30.0) -> bool:
    """Wait for a process that is not this one's child to end (its pidfd turns readable); True once it has."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return True
    try:
        return bool(select.select([fd], [], [], timeout_s)[0])
    finally:
        os.close(fd)


@pytest.fixture
def gone():
    """``gone(pid)``: whether a process that is not the test's child ended within 30 s (awaited, not polled)."""
    return _gone
