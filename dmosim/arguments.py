"""The value types of the command line's flags: each refuses bad input with one line, which the parser prints and
exits 2 on (docs/experiments.md, "Bounds")."""

from __future__ import annotations

import argparse
import datetime as dt
import math

from messages.schemas import MAX_AGENTS
from scenarios.days import MAX_SEED
from scenarios.fleet import MAX_SCALE
from scenarios.horizon import HOURS

from .experiment.spec import MAX_PROFILE_DAYS, MAX_SECONDS


def _shown(text: str) -> str:
    return repr(text if len(text) <= 40 else text[:37] + "...")


def integer(low: int, high: int | None = None):
    """The type of a flag that takes an integer in low..high, or from low on without ``high`` (docs/experiments.md,
    "Bounds")."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:  # also an integer of more digits than Python converts
            value = None
        if value is None or value < low or (high is not None and value > high):
            where = f"in {low:,}..{high:,}" if high is not None else f">= {low:,}"
            raise argparse.ArgumentTypeError(f"expected an integer {where}, got {_shown(text)}")
        return value
    return parse


def number(low: float, high: float = math.inf, *, above: bool = False, allow_inf: bool = False):
    """The type of a flag that takes a finite number in [low, high] ((low, high] if ``above``), or inf if
    ``allow_inf``."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        inside = (low < value if above else low <= value) and value <= high and value < math.inf
        if not (allow_inf and value == math.inf) and not inside:
            where = (f"in {'(' if above else '['}{low:,g}, {high:,.15g}]" if high < math.inf else
                     f"{'>' if above else '>='} {low:,g}, finite") + (" or inf" if allow_inf else "")
            raise argparse.ArgumentTypeError(f"expected a number {where}, got {_shown(text)}")
        return value
    return parse


seed = integer(0, MAX_SEED)
agents = integer(1, MAX_AGENTS)
positive_int = integer(1)
hours = integer(0, HOURS)                      # whole hours of the day
seconds = number(0, MAX_SECONDS, above=True)   # a deadline or time limit
wait = number(0, MAX_SECONDS)                  # how long to wait for something, 0: not at all
nonneg_float = number(0)


def gap(text: str) -> float:
    value = nonneg_float(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"expected a relative gap below 1 (e.g. 0.005), got {text!r}")
    return value


def scales(text: str) -> tuple[float, ...]:
    """Comma-separated numbers in (0, MAX_SCALE], at most MAX_PROFILE_DAYS, e.g. a week's 1,1,1,1,1,0.8,0.8."""
    try:
        values = tuple(float(x) for x in text.split(",", MAX_PROFILE_DAYS))
    except ValueError:
        values = ()
    if not 1 <= len(values) <= MAX_PROFILE_DAYS or not all(0 < v <= MAX_SCALE for v in values):
        raise argparse.ArgumentTypeError(f"expected 1..{MAX_PROFILE_DAYS} numbers in (0, {MAX_SCALE:g}] separated by "
                                         f"commas, got {_shown(text)}")
    return values


def budget(text: str) -> tuple[int, int]:
    """MESSAGES,BYTES: what one sender may send in a phase or hour (messages/budget.py), each a positive integer."""
    try:
        messages, size = (positive_int(x) for x in text.split(",", 2))
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"expected MESSAGES,BYTES (two integers >= 1), got {_shown(text)}") from None
    return messages, size


def market_day(text: str) -> str:
    try:
        return dt.date.fromisoformat(text).isoformat()
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a date YYYY-MM-DD, got {text!r}") from None


def today() -> str:
    return dt.date.today().isoformat()
