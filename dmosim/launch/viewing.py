"""The page of a run (``dmosim run --view``): the observer's process (``dmosim view --run-id``, a reader of the run
with its own credentials bundle) started with the run before its first message, its URL handed back once it serves,
and kept after the run, showing how it ended, until the user stops it (``linger``). It is a process of its own, in
``Roles`` of its own, so that the run's end does not stop it and its end never stops the run."""

from __future__ import annotations

import os
import select
import time
from pathlib import Path
from typing import Callable

from ..view.feed import VIEWER
from .processes import Roles, dmosim_command

VIEWER_START_S = 60.0  # how long the observer may take to serve (its imports on a loaded machine)


class ViewFailed(RuntimeError):
    """The observer's process ended before it served its page."""


class Viewing:
    """The observer of one run: ``start`` it once the DMO listens; a context manager that stops it on the way out."""

    name = VIEWER

    def __init__(self, port: int = 0, url_file: str | None = None, say: Callable[[str], None] = lambda text: None):
        self.port, self.url_file, self.say = port, url_file, say
        self.roles = Roles()
        self.url: str | None = None

    def __enter__(self) -> Viewing:
        return self

    def __exit__(self, *exc) -> None:
        self.roles.stop_all()

    def start(self, run_id: str, connect: str, auth: Path, logs: Path, private: Path) -> str:
        """Start the observer of ``run_id`` connecting to ``connect`` with its bundle in ``auth``; return its URL
        once it serves (it writes the URL to a FIFO in the run's ``private`` directory)."""
        fifo = private / "view.url"
        os.mkfifo(fifo, 0o600)
        fd = os.open(fifo, os.O_RDWR | os.O_NONBLOCK)  # held for reading and writing: never reads as ended
        try:
            role = self.roles.start(VIEWER, dmosim_command(
                "view", "--run-id", run_id, "--connect", connect, "--auth-dir", str(auth), "--port", str(self.port),
                "--url-file", str(fifo)), log=logs / f"{VIEWER}.log")
            self.url = _line(fd, role.process, VIEWER_START_S, logs / f"{VIEWER}.log")
        finally:
            os.close(fd)
        if self.url_file:
            with open(self.url_file, "w") as f:
                f.write(self.url + "\n")
        self.say(f"the run's page: {self.url}")
        return self.url

    def linger(self) -> None:
        """Keep the page up, with the run's end on it, until Ctrl-C or SIGTERM (or the observer ends)."""
        role = self.roles.roles.get(VIEWER)
        if role is None:
            return
        self.say(f"the run is over; its page stays at {self.url} until Ctrl-C")
        try:
            self.roles.exits.get()
        except KeyboardInterrupt:
            pass


def _line(fd: int, process, timeout_s: float, log: Path) -> str:
    """The first line written to ``fd``, once it comes; ``ViewFailed`` if ``process`` ends first or time runs out."""
    deadline, got = time.monotonic() + timeout_s, b""
    while b"\n" not in got:
        ready = select.select([fd], [], [], min(0.5, max(0.0, deadline - time.monotonic())))[0]
        if ready:
            got += os.read(fd, 4096)
        elif process.poll() is not None:
            raise ViewFailed(f"the run's page did not start (exit {process.returncode}; its log: {log})")
        elif time.monotonic() > deadline:
            raise ViewFailed(f"the run's page did not start within {timeout_s:g} s (its log: {log})")
    return got.partition(b"\n")[0].decode()
