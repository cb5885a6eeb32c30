"""What tests of several packages share: a ``dmosim`` command run in this process; and, for the slow tests that start
processes, knowing where a process has got without reading its log: a line it writes to a FIFO, a connection it
makes, its end. The fast tier's rule, that a test not marked ``slow`` starts no process and opens no Zenoh session,
is fast_tier.py's."""

from __future__ import annotations

import os
import select
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from dmosim.cli import main

# fast_tier.py (beside this file) holds the fast tier's rule; tests/project/test_tiers.py runs it on tests of its own
pytest_plugins = ("fast_tier", "pytester")


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


class Fifo:
    """A FIFO that a test's child processes write lines to (``path``, given to them on their command line or in their
    environment) and the test reads as they come (``line``): where a child has got, awaited, not read from its log.
    Held open for reading and writing, so that it never reads as ended between two writers (a role restarted)."""

    def __init__(self, path: Path):
        os.mkfifo(path)
        self.path = path
        self._fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
        self._buffer = b""

    def line(self, pid: int, timeout_s: float = 60.0) -> str:
        """The next line written, once it comes; fails if process ``pid`` ends first or ``timeout_s`` passes."""
        deadline = time.monotonic() + timeout_s
        ended = os.pidfd_open(pid)
        try:
            while b"\n" not in self._buffer:
                ready = select.select([self._fd, ended], [], [], max(0.0, deadline - time.monotonic()))[0]
                if self._fd in ready:
                    self._buffer += os.read(self._fd, 4096)
                elif ready:
                    raise AssertionError(f"process {pid} ended before it wrote a line to {self.path.name}")
                else:
                    raise AssertionError(f"process {pid} wrote no line to {self.path.name} within {timeout_s:g} s")
        finally:
            os.close(ended)
        line, _, self._buffer = self._buffer.partition(b"\n")
        return line.decode()

    def close(self) -> None:
        os.close(self._fd)


@pytest.fixture
def fifo(tmp_path):
    """A ``Fifo`` in the test's directory, closed after the test."""
    made = Fifo(tmp_path / "said.fifo")
    yield made
    made.close()


class Listener:
    """A socket listening on a free loopback port (``port``) for processes told to connect there: ``accept(n)`` returns
    once ``n`` of them have connected (a process trying to reach its DMO or router there has got that far), their
    connections held open until ``close``, which also frees the port for a real server."""

    def __init__(self):
        self._server = socket.create_server(("127.0.0.1", 0))
        self.port = self._server.getsockname()[1]
        self._held: list[socket.socket] = []

    def accept(self, n: int = 1, timeout_s: float = 60.0) -> None:
        self._server.settimeout(timeout_s)
        while len(self._held) < n:
            self._held.append(self._server.accept()[0])

    def close(self) -> None:
        for connection in self._held:
            connection.close()
        self._server.close()


@pytest.fixture
def listener():
    """A ``Listener``, closed after the test."""
    made = Listener()
    yield made
    made.close()


# Module fixtures that run a real market day (file, fixture): the tests that share one go to one xdist worker
# together (the README's --dist loadgroup), so that the day runs once, not once on each worker that has one of them.
# tests/project/test_groups.py checks that the grouping takes effect.
SHARED_DAYS = {("test_determinism.py", "base"), ("test_recording.py", "day"), ("test_untrusted_runs.py", "killed"),
               ("test_groups.py", "shared")}


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's own hook, which reads the groups
def pytest_collection_modifyitems(items):
    for item in items:
        for fixture in getattr(item, "fixturenames", ()):
            if (item.path.name, fixture) in SHARED_DAYS:
                item.add_marker(pytest.mark.xdist_group(f"{item.path.stem}-{fixture}"))
