"""A run of several market days: their dates, each day's seed and profile scaling, and the case a day starts from,
which is the state the day before ended in (stored energy, each unit's state, output and hours in that state).

Day d (1-based) draws its forecast errors and islanding from ``day_seed(seed, d)`` only, so any single day can be
reproduced on its own; day 1 keeps the run's seed as it is, so a one-day run is what it always was.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np

from .case import Case, parse_case
from .horizon import HOURS

DAY_STRIDE = 100_003  # a prime: seeds of different days and runs do not collide for any reasonable seed
# The seeds a user may give (a run's, a fleet member's, an agent's): 0..2**32-1, numpy's legacy seed range. Every
# seed derived from one stays a non-negative integer below 2**33 (a day's: + DAY_STRIDE x 3,659 at most, its
# realised day + 1,000), which numpy's SeedSequence takes and which JSON and MCAP metadata keep exactly.
MAX_SEED = 2**32 - 1


def check_seed(seed: object, what: str = "seed") -> int:
    """``seed`` if it is an integer in 0..MAX_SEED, else ValueError naming ``what``."""
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise ValueError(f"{what} must be an integer in 0..{MAX_SEED}, got {seed!r}")
    return seed


def market_days(first: str, days: int) -> tuple[str, ...]:
    """The ISO dates of ``days`` consecutive market days from ``first``; ValueError if the last would fall after
    9999-12-31, the last date there is."""
    start = dt.date.fromisoformat(first)
    if days > (dt.date.max - start).days + 1:
        raise ValueError(f"{days} market days from {first} end after {dt.date.max.isoformat()}, the last date there is")
    return tuple((start + dt.timedelta(days=d)).isoformat() for d in range(days))


def day_seed(seed: int, day: int) -> int:
    """The seed of day ``day`` (1-based) of a run seeded ``seed``."""
    return int(seed) + DAY_STRIDE * (int(day) - 1)


def day_scale(scales: tuple[float, ...] | list[float], day: int) -> float:
    """The scale of day ``day`` (1-based) from a weekly (or any length) pattern, repeated: e.g. weekday/weekend."""
    return float(scales[(day - 1) % len(scales)]) if scales else 1.0


@dataclass(frozen=True)
class Midnight:
    """What a microgrid carries into the next day, as its realised operation ended the day: per unit (in case
    order) whether it is on, its output (MW) and the whole hours it has been in that state (1..24, 24 meaning
    at least a day); and the stored energy (MWh), if it has a storage."""

    unit_on: tuple[bool, ...]
    unit_output_mw: tuple[float, ...]
    unit_hours: tuple[int, ...]
    stored_mwh: float | None


def hours_in_state(commitment: np.ndarray) -> tuple[int, ...]:
    """Per unit, the whole hours it has been in its hour-24 state at midnight, from its (G, 24) 0/1 commitment: the
    run at the end of the day, 24 if it never changed (a day is as long as any minimum up or down time)."""
    out = []
    for row in np.asarray(commitment) > 0.5:
        changes = np.flatnonzero(row != row[-1])
        out.append(int(HOURS - 1 - changes[-1]) if len(changes) else HOURS)
    return tuple(out)


def carry_over(case: Case, midnight: Midnight, name: str | None = None) -> Case:
    """``case`` starting from ``midnight``: units in their states, outputs and hours, storage at its energy. The
    model's end-of-day storage condition then holds against this energy (docs/model.md)."""
    data = case.model_dump()
    for unit, on, output, hours in zip(data["units"], midnight.unit_on, midnight.unit_output_mw, midnight.unit_hours):
        output = min(max(float(output), unit["p_min"]), unit["p_max"]) if on else None  # solver noise off the limits
        unit.update(initial_on=bool(on), p_initial=output, initial_hours=int(hours))
    if data.get("storage") is not None and midnight.stored_mwh is not None:
        data["storage"]["c_initial"] = min(max(float(midnight.stored_mwh), 0.0), data["storage"]["c_max"])
    if name is not None:
        data["case"]["name"] = name
    return parse_case(data, f"case {case.name} after midnight")


def scaled_profiles(case: Case, load: float, renewable: float) -> Case:
    """``case`` with its fixed-load forecast times ``load`` and its renewable forecasts times ``renewable`` (a day
    of lighter demand, a cloudier day), renewables capped at their capacity."""
    if load == 1.0 and renewable == 1.0:
        return case
    data = case.model_dump()
    data["fixed_load"]["forecast"] = [x * load for x in data["fixed_load"]["forecast"]]
    for unit in data["renewables"]:
        unit["forecast"] = [min(x * renewable, unit["capacity"]) for x in unit["forecast"]]
    return parse_case(data, f"case {case.name} scaled (load x{load:g}, renewables x{renewable:g})")
