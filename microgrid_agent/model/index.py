"""How hourly first-stage decisions reach the (member x scenario, sub-period) rows of the second stage.

Second-stage variables of a family with several members (units, loads, renewables) are stacked member-major, row
``m * S + s``, one column per sub-period ``n = (t-1) K + tau - 1``. Hourly variables enter those rows through the
constant matrices below, so every constraint family is one array expression, with no Python loop over scenarios
or sub-periods.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import scipy.sparse as sp

from scenarios.horizon import HOURS, per_subperiod, subperiod_hours


class Index:
    """Constant matrices that map hourly first-stage variables onto stacked (member x scenario, sub-period) rows."""

    def __init__(self, S: int, K: int):
        self.S, self.K, self.N = S, K, HOURS * K
        self.dt = subperiod_hours(K)
        # E (24, N): hour t -> its K sub-periods.
        self.E = sp.kron(sp.eye(HOURS), np.ones((1, K)), format="csr")

    def rows(self, m: int) -> sp.csr_matrix:
        """(m S, m): copies each of m members' hourly row to its S scenario rows."""
        return sp.kron(sp.eye(m), np.ones((self.S, 1)), format="csr")

    def total(self, m: int) -> sp.csr_matrix:
        """(S, m S): sums m members' rows per scenario."""
        return sp.kron(np.ones((1, m)), sp.eye(self.S), format="csr")

    def expand(self, hourly: cp.Expression, m: int) -> cp.Expression:
        """(m, 24) hourly variable -> (m S, N) sub-period rows."""
        return self.rows(m) @ hourly @ self.E

    def per_scenario(self, hourly: np.ndarray) -> np.ndarray:
        """(24,) hourly constants -> (S, N): held over each hour's sub-periods, the same in every scenario."""
        return np.tile(per_subperiod(hourly, self.K), (self.S, 1))

    def per_row(self, values: np.ndarray) -> np.ndarray:
        """(m,) member constants -> (m S, N) array."""
        return np.repeat(np.asarray(values, float), self.S)[:, None] * np.ones((1, self.N))


def previous(first: np.ndarray | cp.Expression, x: cp.Expression) -> cp.Expression:
    """x shifted one sub-period later along axis 1, with ``first`` (rows,) as the value before the day."""
    return cp.hstack([cp.reshape(first, (x.shape[0], 1), order="C"), x[:, :-1]])


def hour_row(x: cp.Expression) -> cp.Expression:
    """A (24,) hourly variable as a (1, 24) row, the shape of one member's hourly state."""
    return cp.reshape(x, (1, HOURS), order="C")
