"""The QP of the AC-faithful clearing's proximal iterations, against closed forms, with scipy linprog's signs."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import linprog

from dmo.market.quadratic import minimise


def test_a_bounded_parabola_meets_its_closed_form_and_its_duals_signs_are_linprogs():
    # min (x0^2 + x1^2) / 2 - x0 - 2 x1 s.t. x0 + x1 <= 1, x0 - x1 = -0.5, 0 <= x <= 10: by the KKT conditions
    # x = (0.25, 0.75); the equality's and the inequality's multipliers solve 0.25 - 1 + m + e = 0,
    # 0.75 - 2 + m - e = 0: m = 1, e = -0.25; as marginals (d objective / d right side), -1 and 0.25.
    res = minimise(np.array([-1.0, -2.0]), sp.identity(2, format="csc"), np.array([[1.0, -1.0]]), np.array([-0.5]),
                   np.array([[1.0, 1.0]]), np.array([1.0]), np.zeros(2), np.full(2, 10.0))
    assert res.status == 0
    assert res.x == pytest.approx([0.25, 0.75], abs=1e-7)
    assert res.ineqlin.marginals == pytest.approx([-1.0], abs=1e-6)
    assert res.eqlin.marginals == pytest.approx([0.25], abs=1e-6)


def test_with_no_curvature_it_is_linprogs_lp():
    c, a_ub, b_ub = np.array([-3.0, -2.0]), np.array([[1.0, 1.0], [1.0, 0.0]]), np.array([4.0, 3.0])
    res = minimise(c, sp.csc_array((2, 2)), np.zeros((0, 2)), np.zeros(0), a_ub, b_ub, np.zeros(2), np.full(2, 9.0))
    ref = linprog(c, A_ub=a_ub, b_ub=b_ub, bounds=[(0, 9)] * 2, method="highs")
    assert res.x == pytest.approx(ref.x, abs=1e-9) and res.fun == pytest.approx(ref.fun, abs=1e-9)
    assert res.ineqlin.marginals == pytest.approx(ref.ineqlin.marginals, abs=1e-9)
    assert res.lower.marginals == pytest.approx(ref.lower.marginals, abs=1e-9)
    assert res.upper.marginals == pytest.approx(ref.upper.marginals, abs=1e-9)


def test_an_infeasible_qp_says_so():
    res = minimise(np.zeros(1), sp.identity(1, format="csc"), np.zeros((0, 1)), np.zeros(0),
                   np.array([[1.0]]), np.array([-1.0]), np.zeros(1), np.ones(1))
    assert res.status != 0
