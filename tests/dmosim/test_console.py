"""What every command prints through (dmosim/console.py): the progress of a long run, on a terminal and off it."""

from __future__ import annotations

import io

from dmosim.console import Progress, duration


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


class _Clock:
    """A clock the test moves: the estimate depends on nothing else."""

    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def _week(stream: _Stream, clock: _Clock) -> Progress:
    """A week's clock as ``dmosim run`` follows it, 10 s an hour, a fault line on day 2."""
    bar = Progress("hours", stream, clock)
    for done in range(0, 7 * 24 + 1):
        bar.update(done, 7 * 24, f"day {done // 24 + 1}/7, phase realtime")
        if done == 30:
            bar.say("fault: killing mg1 (SIGKILL) at hour 7 of day 2")
        clock.now += 10
    bar.close()
    return bar


def test_off_a_terminal_a_week_is_a_line_per_tenth_not_a_line_per_hour():
    stream, clock = _Stream(tty=False), _Clock()
    _week(stream, clock)
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue() and "\x1b" not in stream.getvalue()
    assert len(lines) == 12  # 0%, 10%, ..., 100%, and the fault
    assert lines[0] == "dmosim: 0/168 hours (0%), time left not known yet"
    assert lines[1] == "dmosim: 17/168 hours (10%), about 25 min 10 s left"  # 170 s for 17 h: 10 s an hour
    assert lines[2] == "dmosim: fault: killing mg1 (SIGKILL) at hour 7 of day 2"
    assert lines[-1] == "dmosim: 168/168 hours (100%), done"


def test_on_a_terminal_a_week_is_one_line_redrawn_with_the_lines_said_above_it():
    stream, clock = _Stream(tty=True), _Clock()
    _week(stream, clock)
    text = stream.getvalue()
    assert text.count("\n") == 2  # the fault's line, and the last bar left on its own line
    said, last = text.split("\n")[:2]
    assert said.endswith("\r\x1b[Kdmosim: fault: killing mg1 (SIGKILL) at hour 7 of day 2")
    assert last.rsplit("\r", 1)[-1] == "dmosim: 168/168 hours (100%), done; day 8/7, phase realtime\x1b[K"
    redrawn = last.split("\r")
    assert "dmosim: 31/168 hours (18%), about 22 min 50 s left; day 2/7, phase realtime\x1b[K" in redrawn


def test_durations_read_as_a_person_reads_them():
    assert [duration(s) for s in (0.4, 59, 200, 3599, 7500)] == ["0 s", "59 s", "3 min 20 s", "59 min 59 s",
                                                                  "2 h 05 min"]
