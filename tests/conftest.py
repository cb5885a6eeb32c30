"""What tests of several packages share: a ``dmosim`` command run in this process, and waiting for a process that is
not the test's own child to end."""

from __future__ import annotations

import os
import select
from dataclasses import dataclass

import pytest

from dmosim.cli import main


@dataclass(frozen=True)
class Said:
    """What a command ended with: its exit code, and what it printed on stdout and on stderr."""

    returncode: int
    stdout: str
    stderr: str


@pytest.fixture
def cli(capsys):
    """``cli(*args)``: ``dmosim ARGS`` run in this process as the executable runs it (``main``), and what it said.
    Give solves that would spread over processes ``--workers 1``."""
    capsys.readouterr()

    def run(*args: str) -> Said:
        code = main(list(args))
        said = capsys.readouterr()
        return Said(code, said.out, said.err)
    return run


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
