"""The day's time grid: an hourly profile held over each hour's sub-periods, and their length."""

from __future__ import annotations

import numpy as np
import pytest

from scenarios.horizon import HOURS, per_subperiod, subperiod_hours


@pytest.mark.parametrize("k", [1, 2, 6])
def test_an_hourly_profile_holds_its_value_over_each_hours_subperiods(k):
    hourly = np.arange(HOURS, dtype=float) * 1.5
    out = per_subperiod(hourly, k)
    assert out.shape == (HOURS * k,)
    assert all(out[h * k + j] == hourly[h] for h in range(HOURS) for j in range(k))
    assert subperiod_hours(k) * k == 1.0


def test_the_last_axis_is_expanded_unless_told_otherwise():
    table = np.arange(2 * HOURS).reshape(2, HOURS)
    assert per_subperiod(table, 3).shape == (2, 3 * HOURS)
    assert (per_subperiod(table, 3)[1, 3:6] == table[1, 1]).all()
    assert per_subperiod(table.T, 3, axis=0).shape == (3 * HOURS, 2)
