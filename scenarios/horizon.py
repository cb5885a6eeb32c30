"""The market day's time grid: 24 hours, each split into sub-periods (their length, an hourly profile held over
them), and the check of an hourly profile.

Every package counts the day in these hours, so they are defined once, here, at the bottom of the import flow.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import numpy as np

HOURS = 24


def subperiod_hours(subperiods: int) -> float:
    """dt, the length of a sub-period in hours, at K = ``subperiods`` sub-periods an hour: 1/K."""
    return 1.0 / subperiods


def per_subperiod(hourly, subperiods: int, axis: int = -1) -> np.ndarray:
    """An hourly profile (24 long along ``axis``, the last by default) held over each hour's K = ``subperiods``
    sub-periods: 24 K long, sub-period n = h K + k in hour h."""
    return np.repeat(hourly, subperiods, axis=axis)


def finite(x: float, what: str) -> float:
    """``x`` as a float, or ValueError naming ``what`` when it is not a finite real number."""
    if isinstance(x, bool) or not isinstance(x, numbers.Real):
        raise ValueError(f"{what} must be a number, got {x!r}")
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"{what} must be finite, got {x}")
    return x


def hourly(values: float | Sequence[float], what: str, *, non_negative: bool = False) -> tuple[float, ...]:
    """24 finite values from a scalar (the same every hour) or a 24-long sequence; ValueError otherwise."""
    if isinstance(values, numbers.Real) and not isinstance(values, bool):
        values = [values] * HOURS
    if isinstance(values, (str, bytes)) or not isinstance(values, (Sequence, np.ndarray)):
        raise ValueError(f"{what} must be a number or {HOURS} numbers, got {type(values).__name__}")
    if len(values) != HOURS:
        raise ValueError(f"{what} must have {HOURS} hourly values, got {len(values)}")
    out = tuple(finite(v, f"{what} at hour index {h}") for h, v in enumerate(values))
    if non_negative and any(v < 0 for v in out):
        h = next(h for h, v in enumerate(out) if v < 0)
        raise ValueError(f"{what} must be >= 0, got {out[h]} at hour index {h}")
    return out
