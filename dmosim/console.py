"""What every command shares at the terminal: the user-input error, progress lines, JSON output."""

from __future__ import annotations

import importlib.util
import json
import math
import os
import shutil
import signal
import stat
import sys
import threading
import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TextIO


class UsageError(Exception):
    """Bad input from the user: printed as one line, exit 2."""


# A role's log line: its time, who says it, the level and the message. Each process names itself (``role``); agents
# sharing a process (``dmosim run --per-process``) are named by their threads.
LOG_FORMAT = "%(asctime)s {role} %(levelname)s %(message)s"
LOG_DATEFMT = "%H:%M:%S"
SIBLINGS = ("scenarios", "messages", "microgrid_agent", "dmo")  # the packages installed beside dmosim
_HOME = Path(__file__).resolve().parents[1]  # where they are: the directory that holds dmosim/


def shadowing(packages: tuple[str, ...] = SIBLINGS, home: Path = _HOME) -> str | None:
    """The one line saying which file Python would import instead of one of our ``packages``, else None.

    ``python -m`` and scripts put the current directory first on ``sys.path``, so a user's own ``scenarios.py``
    (or ``messages/``) there is found before the package installed beside dmosim, and an import of ours fails far
    away from the cause. Found without importing (``find_spec`` of a top-level name runs nothing)."""
    for name in packages:
        module = sys.modules.get(name)
        spec = module.__spec__ if module is not None else importlib.util.find_spec(name)
        if spec is None:
            continue  # not installed at all: the import itself says so
        found = spec.origin or next(iter(spec.submodule_search_locations or ()), None)
        if found is None or Path(found).resolve() != (home / name / "__init__.py").resolve():
            return (f"{found or name} shadows dmosim's package {name!r} (Python finds it first on sys.path: the "
                    "current directory, with python -m, or PYTHONPATH); rename it, or run the installed dmosim "
                    "command from another directory (README.md)")
    return None


def refuse_shadowed_packages() -> None:
    """Exit 2 with ``shadowing``'s line, before anything of ours imports the wrong package."""
    why = shadowing()
    if why is not None:
        print(f"error: {why}", file=sys.stderr)
        raise SystemExit(2)


def stop_on_terminate():
    """Take SIGTERM as Ctrl-C from now on: a command that started processes of its own (``dmosim run`` its roles,
    ``sweep`` and ``bench`` their runs) stops them on its way out (its ``except`` and ``finally``) and exits 130,
    instead of dying and leaving them running. Python runs the handler between bytecodes, so only where the main
    thread waits in Python, not in a long native call (a solve). Returns the handler it replaced."""
    return signal.signal(signal.SIGTERM, _interrupt)


@contextmanager
def stopping_on_terminate():
    """``stop_on_terminate`` for the block only (a benchmark while it has processes of its own), the handler it
    replaced restored after it."""
    previous = stop_on_terminate()
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _interrupt(*_):
    raise KeyboardInterrupt


def last_words(line: str) -> None:
    """Say ``line`` on stderr as the last thing this process says, and never wait for a reader to do it: what stdout
    and stderr cannot take at once (a pipe nobody reads, whose 64 KiB a ``--json`` of 100 kB outgrows) is dropped.
    An interrupted command (Ctrl-C, SIGTERM) says so and exits, whoever reads its output, instead of waiting for ever
    to finish writing it (the flush at exit would wait too)."""
    _write_now(sys.stdout, "")
    _write_now(sys.stderr, line + "\n")


def _write_now(stream: TextIO, text: str) -> None:
    """Write ``text`` and what ``stream`` holds back, as far as its pipe or socket takes it without waiting; what it
    does not take is dropped, the stream pointed at /dev/null. A file or a terminal is written as usual."""
    if stream.closed:
        return
    try:
        fd = stream.fileno()
        mode = os.fstat(fd).st_mode
        waits = stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)
    except (OSError, ValueError):  # no descriptor of its own (a test's capture)
        waits = False
    if not waits:
        stream.write(text)
        stream.flush()
        return
    os.set_blocking(fd, False)
    try:
        stream.write(text)
        stream.flush()
        full = False
    except BlockingIOError:
        full = True
    finally:
        os.set_blocking(fd, True)  # the pipe is shared: whoever writes to it next expects it to wait
    if full:
        os.dup2(os.open(os.devnull, os.O_WRONLY), fd)  # what is still held back goes nowhere, at once


def progress(message: str) -> None:
    print(f"dmosim: {message}", file=sys.stderr, flush=True)


class Progress:
    """How far a long command has got (hours of a run, runs of a sweep) and an estimate of the time left.

    On a terminal (``stream`` is a tty), one line that updates in place, with what is happening now after it; the
    lines ``say`` prints go above it. Elsewhere (a log, CI), where a line rewritten in place would pile up, a plain
    line each time another tenth of the work is done. The estimate assumes the rest goes at the pace so far."""

    STEPS = 10  # the plain lines of a whole run, off a terminal

    def __init__(self, unit: str, stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic):
        self.unit, self.stream, self.clock = unit, stream or sys.stderr, clock
        self.tty = self.stream.isatty()
        self.started = clock()
        self.lock = threading.Lock()  # updates come from the bus's threads too
        self.shown = ""  # the bar now on screen (tty), or ""
        self.step = -1  # the last tenth reported (off a terminal)

    def say(self, message: str) -> None:
        """A line of its own (a fault fired, a run failed), above the bar."""
        with self.lock:
            bar = self.shown
            self._draw("")
            self.stream.write(f"dmosim: {message}\n")
            self.stream.flush()
            self._draw(bar)

    def update(self, done: int, total: int, note: str = "", left: str | None = None) -> None:
        """``done`` of ``total`` units are done; ``note`` says what is under way; ``left`` the time left in words
        (None: as the pace so far gives it, ``left``)."""
        with self.lock:
            left = "done" if done >= total else left or self.left(done, total)
            line = f"{done}/{total} {self.unit} ({100 * done // max(total, 1)}%), {left}"
            if self.tty:
                self._draw(f"dmosim: {line}" + (f"; {note}" if note else ""))
            elif (step := self.STEPS * done // max(total, 1)) > self.step:
                self.step = step
                self.stream.write(f"dmosim: {line}\n")
                self.stream.flush()

    def left(self, done: int, total: int) -> str:
        """The time left as the pace so far gives it."""
        if done >= total:
            return "done"
        elapsed = self.clock() - self.started
        if done <= 0 or elapsed <= 0:
            return "time left not known yet"
        return f"about {duration(elapsed / done * (total - done))} left"

    def close(self) -> None:
        """Leave the last bar on its own line, so that what is printed next starts on a fresh one."""
        with self.lock:
            if self.shown:
                self.stream.write("\n")
                self.stream.flush()
            self.shown = ""

    def _draw(self, bar: str) -> None:
        """Replace the line on screen by ``bar`` (cut to the terminal's width: a wrapped line cannot be redrawn)."""
        if not self.tty or bar == self.shown == "":
            return
        width = shutil.get_terminal_size().columns - 1
        self.stream.write("\r" + bar[:width] + "\x1b[K")
        self.stream.flush()
        self.shown = bar


@dataclass(frozen=True)
class Mark:
    """A clock message of a run as the launcher saw it: when (``t``, s), the day (1..), the phase starting and, in
    real time, the hour (1..24)."""

    t: float
    day: int
    phase: str
    hour: int | None = None


def run_time_left(marks: Sequence[Mark], days: int, now: float) -> float | None:
    """Seconds a run of ``days`` market days has left at ``now``, from the work its phases took so far (``marks``,
    in order), or None while nothing measured covers the work ahead. A day is its front (from the previous day's
    settlement, or the run's first mark, to its hour 1: bidding, clearing and the agents' solves, most of a day's
    time) and its 24 real-time hours, each priced at the mean of those measured; the time already spent in the
    current phase or hour is taken off its share. The pace of hours done over time spent, which a front of solves
    skews, is not used: the first hours of a run would predict the rest at the solves' pace."""
    from scenarios.horizon import HOURS  # noqa: PLC0415  (imported after the check that no file shadows scenarios)

    if not marks:
        return None
    fronts, hours, start, last = [], [], marks[0].t, None
    for mark in marks:
        if mark.phase == "realtime" and mark.hour == 1:
            fronts.append(mark.t - start)
        elif mark.phase == "settlement":
            start = mark.t
        if last is not None and last.phase == "realtime":
            hours.append(mark.t - last.t)
        last = mark
    front = sum(fronts) / len(fronts) if fronts else None
    hour = sum(hours) / len(hours) if hours else None
    since = now - last.t
    if last.phase == "realtime":
        if hour is None:
            return None
        here = max((HOURS - last.hour + 1) * hour - since, 0.0)
    elif last.phase == "settlement":
        here = 0.0
    else:  # in the day's front: its solves
        if front is None or hour is None:
            return None
        here = max(front - (now - start), 0.0) + HOURS * hour
    ahead = days - last.day
    if ahead and (front is None or hour is None):
        return None
    return here + ahead * ((front or 0.0) + HOURS * (hour or 0.0))


def left_words(seconds: float | None) -> str:
    """The time left as ``Progress`` says it: an estimate is "about"; none is said to be not known yet."""
    if seconds is None:
        return "time left not known yet"
    return "under a second left" if seconds < 0.5 else f"about {duration(seconds)} left"


def duration(seconds: float) -> str:
    """Seconds as a person reads them: 45 s, 3 min 20 s, 2 h 05 min."""
    s = round(seconds)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def jsonable(obj):
    """JSON has no infinity: an infinite penalty or bound is written as the string "inf"."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else ("inf" if obj > 0 else "-inf")
    if isinstance(obj, dict):
        return {k: jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    return obj


def print_json(obj) -> None:
    json.dump(jsonable(obj), sys.stdout, indent=2)
    sys.stdout.write("\n")
