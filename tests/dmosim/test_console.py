"""What every command prints through (dmosim/console.py): the progress of a long run, on a terminal and off it."""

from __future__ import annotations

import io

import pytest

from dmosim.console import Mark, Progress, duration, left_words, run_time_left


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


def _marks(days: int, front_s: float, hour_s: float, upto: tuple[int, str, int | None]) -> list[Mark]:
    """The clock messages of a run whose every day takes ``front_s`` before hour 1 and ``hour_s`` an hour, up to and
    including ``upto`` (day, phase, hour)."""
    out, t = [], 0.0
    for day in range(1, days + 1):
        for phase in ("bidding", "clearing", "scheduling"):
            out.append(Mark(t, day, phase))
            t += front_s / 3
            if (day, phase, None) == upto:
                return out
        for hour in range(1, 25):
            out.append(Mark(t, day, "realtime", hour))
            if (day, "realtime", hour) == upto:
                return out
            t += hour_s
        out.append(Mark(t, day, "settlement"))
        if (day, "settlement", None) == upto:
            return out
    return out


def test_the_time_left_comes_from_the_phases_work_not_the_pace_of_hours():
    """A day of 4.3 minutes: 200 s of solves before hour 1, then 24 hours of 2.5 s. At hour 2 the pace of hours done
    (1 hour in 202.5 s) would say 78 min; the phases say the 23 hours left, 57.5 s."""
    marks = _marks(1, 200.0, 2.5, (1, "realtime", 2))
    assert run_time_left(marks, 1, marks[-1].t) == pytest.approx(23 * 2.5)
    assert run_time_left(marks, 1, marks[-1].t + 1.0) == pytest.approx(23 * 2.5 - 1.0)  # part of hour 2 is spent
    # two days: the second day's front and hours priced by the first's
    marks = _marks(2, 200.0, 2.5, (1, "realtime", 2))
    assert run_time_left(marks, 2, marks[-1].t) == pytest.approx(23 * 2.5 + 200.0 + 24 * 2.5)
    marks = _marks(2, 200.0, 2.5, (2, "scheduling", None))  # in day 2's solves: what the first day's front left
    assert run_time_left(marks, 2, marks[-1].t) == pytest.approx(200.0 / 3 + 24 * 2.5)
    assert run_time_left(_marks(2, 200.0, 2.5, (1, "settlement", None)), 2, 203.0 + 60) == pytest.approx(
        200.0 + 24 * 2.5)


def test_no_estimate_is_said_before_the_work_ahead_was_measured_once():
    assert run_time_left([], 1, 0.0) is None
    assert run_time_left(_marks(1, 90.0, 1.0, (1, "scheduling", None)), 1, 80.0) is None  # the first solves
    assert run_time_left(_marks(1, 90.0, 1.0, (1, "realtime", 1)), 1, 90.5) is None  # no hour has ended yet
    assert left_words(None) == "time left not known yet" and left_words(57.5) == "about 58 s left"
    assert left_words(0.2) == "under a second left"
