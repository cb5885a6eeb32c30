"""A run of several days: dates, seeds, scaled profiles and the case a day starts from (scenarios/days.py)."""

from __future__ import annotations

import numpy as np
import pytest

from scenarios.case import CaseError, load_case
from scenarios.days import Midnight, carry_over, day_scale, day_seed, hours_in_state, market_days, scaled_profiles
from scenarios.horizon import HOURS


def test_days_have_their_dates_and_seeds_and_day_one_keeps_the_runs_seed():
    assert market_days("2026-02-27", 3) == ("2026-02-27", "2026-02-28", "2026-03-01")
    assert day_seed(7, 1) == 7 and len({day_seed(s, d) for s in range(5) for d in range(1, 8)}) == 35
    assert [day_scale((1.0, 0.8), d) for d in range(1, 6)] == [1.0, 0.8, 1.0, 0.8, 1.0] and day_scale((), 3) == 1.0


def test_hours_in_state_count_back_from_midnight():
    rows = np.array([[1] * HOURS, [0] * 22 + [1, 1], [1] * 23 + [0], [0] * HOURS])
    assert hours_in_state(rows) == (24, 2, 1, 24)


def test_a_day_starts_where_the_last_one_ended():
    case = load_case("paper")
    g = len(case.units)
    midnight = Midnight(unit_on=(True,) * (g - 1) + (False,), unit_output_mw=(9.0,) + (1.2,) * (g - 1),
                        unit_hours=(3,) * g, stored_mwh=4.5)
    after = carry_over(case, midnight, name="paper-day2")
    assert after.name == "paper-day2" and after.storage.c_initial == 4.5
    assert [u.initial_on for u in after.units] == list(midnight.unit_on)
    assert after.units[0].p_initial == after.units[0].p_max  # 9 MW clipped to the unit's limit
    assert after.units[-1].p_initial is None and after.units[-1].initial_hours == 3
    assert after.units[-1].keep_initial_hours == max(0, after.units[-1].min_down - 3)
    assert carry_over(case, Midnight(midnight.unit_on, midnight.unit_output_mw, midnight.unit_hours, 99.0)
                      ).storage.c_initial == case.storage.c_max
    with pytest.raises(CaseError):
        carry_over(case, Midnight(midnight.unit_on, midnight.unit_output_mw, (0,) * g, 1.0))  # hours >= 1


def test_profiles_scale_and_renewables_stay_within_capacity():
    case = load_case("paper")
    lighter = scaled_profiles(case, 0.8, 3.0)
    np.testing.assert_allclose(lighter.fixed_load.forecast, np.asarray(case.fixed_load.forecast) * 0.8)
    for before, after in zip(case.renewables, lighter.renewables):
        np.testing.assert_allclose(after.forecast, np.minimum(np.asarray(before.forecast) * 3.0, before.capacity))
    assert scaled_profiles(case, 1.0, 1.0) is case
