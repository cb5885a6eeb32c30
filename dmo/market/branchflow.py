"""The AC power flow of a radial feeder as the exact branch-flow (DistFlow) equations, and its loss factors.

Baran and Wu (1989) write the AC power flow of a radial feeder without shunts line by line; for line l from bus i
to bus j, with P_l, Q_l the flows leaving i, U = V^2 and l_l = |I_l|^2:

    P_l = p_j + sum of P_m over the lines m leaving j + r_l l_l        Q_l likewise with q_j and x_l
    U_j = U_i - 2 (r_l P_l + x_l Q_l) + (r_l^2 + x_l^2) l_l             l_l = (P_l^2 + Q_l^2) / U_i

Dropping the l_l terms is LinDistFlow (``scenarios.network.Network.lindistflow``). ``BranchFlow.solve`` solves them
whole by sweeps: flows from the losses of the last sweep, voltages from the flows, losses from both, until the
losses no longer move (a few sweeps on a distribution feeder). Its losses' sensitivities to each bus's P and Q (the
marginal loss factors, exact to first order) come from the adjoint of the same equations, solved by sweeps too.
Everything is sparse products in a fixed order: the same bits on any CPU (no BLAS). Pure: arrays in, arrays out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from scenarios.network import Network

# The sweeps stop when the squared currents (p.u.) move less than this, relative to their largest: far below what
# any limit or price needs, and reached in a handful of sweeps on a feeder whose losses are a few per cent.
SWEEP_TOLERANCE = 1e-14
MAX_SWEEPS = 200  # a feeder loaded near its voltage collapse converges slowly or not at all: no AC solution then


@dataclass(frozen=True, eq=False)
class OperatingPoint:
    """The AC solution of the feeder at bus loads ``p`` (MW) and ``q`` (Mvar, + consumption; the substation's
    ignored): per line the flows ``flow_p``, ``flow_q`` leaving its parent bus (MW, Mvar, away from the substation)
    and ``current2`` (|I|^2, p.u.); per bus ``u`` (V^2, p.u.); ``losses`` (MW), so that the substation imports the
    loads' sum plus ``losses``. ``sweeps``: how many the solution took."""

    p: np.ndarray
    q: np.ndarray
    flow_p: np.ndarray
    flow_q: np.ndarray
    current2: np.ndarray
    u: np.ndarray
    losses: float
    sweeps: int

    @property
    def v(self) -> np.ndarray:
        return np.sqrt(self.u)

    def of(self, p: np.ndarray, q: np.ndarray) -> bool:
        """Whether this is the solution at the loads ``p``, ``q`` exactly (the same bits)."""
        return np.array_equal(self.p, p) and np.array_equal(self.q, q)


class BranchFlow:
    """A network's branch-flow equations, sparse: ``solve`` gives the AC operating point at given loads,
    ``loss_factors`` the marginal losses there."""

    def __init__(self, network: Network):
        self.network = network
        d = sp.csr_array(network.downstream)  # lines x buses: bus b is at or below line l
        self.D, self.DT = d, d.T.tocsr()
        below = d[:, network.child].tocsr()  # lines x lines: line m is at or below line l
        self.below = below
        self.strictly_below = (below - sp.eye_array(network.n_lines, format="csr")).tocsr()
        self.path = below.T.tocsr()  # lines x lines: line m is on the path from the substation to line l, l included
        self.r, self.x = network.r_pu, network.x_pu
        self.z2 = self.r ** 2 + self.x ** 2
        self.u0 = network.v_substation ** 2

    def solve(self, p: np.ndarray, q: np.ndarray, near: OperatingPoint | None = None) -> OperatingPoint | None:
        """The AC solution at bus loads ``p``, ``q`` (MW, Mvar), or None if the sweeps find none (a voltage that
        collapses, or no convergence within MAX_SWEEPS). The sweeps start from LinDistFlow (no losses), or from
        the currents of ``near``, a solution at loads close by (fewer sweeps, the same solution)."""
        p, q = np.asarray(p, float), np.asarray(q, float)
        base_p, base_q = self.D @ p, self.D @ q

        def state(current2):  # the flows and voltages the currents give: the backward and forward sweep
            flow_p = base_p + self.below @ (self.r * current2)
            flow_q = base_q + self.below @ (self.x * current2)
            return flow_p, flow_q, self.u0 - self.DT @ (2 * (self.r * flow_p + self.x * flow_q) - self.z2 * current2)

        current2 = np.zeros(self.network.n_lines) if near is None else near.current2
        for sweep in range(1, MAX_SWEEPS + 1):
            flow_p, flow_q, u = state(current2)
            if not np.isfinite(u).all() or u.min() <= 0:
                return None
            new = (flow_p ** 2 + flow_q ** 2) / self._sending(u)
            moved = np.abs(new - current2).max(initial=0.0)
            current2 = new
            if moved <= SWEEP_TOLERANCE * max(1.0, current2.max(initial=0.0)):
                flow_p, flow_q, u = state(current2)
                return OperatingPoint(p, q, flow_p, flow_q, current2, u, math.fsum(self.r * current2), sweep)
        return None

    def _sending(self, u: np.ndarray) -> np.ndarray:
        """U at each line's parent bus."""
        return u[self.network.parent]

    def loss_factors(self, point: OperatingPoint) -> tuple[np.ndarray, np.ndarray]:
        """Per bus, d losses / d p_j and d losses / d q_j at ``point`` (MW per MW, per Mvar; 0 at the substation)."""
        lf_p, lf_q = self.sensitivities(point, g_l=self.r[:, None])
        return lf_p[0], lf_q[0]

    def sensitivities(self, point: OperatingPoint, g_p=None, g_q=None, g_l=None, g_u=None) -> tuple[np.ndarray, ...]:
        """The sensitivities at ``point`` of k quantities that are each linear in the lines' flows, currents and
        voltages, y = sum g_p P + g_q Q + g_l l + g_u U (each g, lines x k, 0 if not given; g_u's row l is the
        voltage at line l's child bus): dy/dp and dy/dq (k x buses, 0 at the substation), to first order.

        The adjoint of the branch-flow equations: with multipliers a, b (the flows' equations), c (the currents')
        and d (the voltages') per line, a_l = a_parent + g_p + 2 P_l c_l - 2 r_l d_l, b_l likewise with g_q, Q_l
        and x_l, U_i c_l = g_l + r_l a_l + x_l b_l + z_l^2 d_l, and d_l = the sum of g_u over the lines at or below
        l less that of l_m c_m over the lines m strictly below it; dy/dp_j is a (dy/dq_j is b) of the line feeding
        bus j. Solved by sweeps from LinDistFlow's answer (c = 0): each coupling is a resistance times a flow,
        small on any feeder that has an AC solution."""
        n = self.network.n_lines
        k = next(g.shape[1] for g in (g_p, g_q, g_l, g_u) if g is not None)
        zero = np.zeros((n, k))
        g_p, g_q, g_l, g_u = (zero if g is None else np.asarray(g, float) for g in (g_p, g_q, g_l, g_u))
        sending = self._sending(point.u)[:, None]
        flow_p, flow_q, current2 = point.flow_p[:, None], point.flow_q[:, None], point.current2[:, None]
        r, x, z2 = self.r[:, None], self.x[:, None], self.z2[:, None]
        d_fixed = self.below @ g_u

        def flows(c, d):  # the flows' multipliers a, b, summed down each line's path
            return self.path @ (g_p + 2 * flow_p * c - 2 * r * d), self.path @ (g_q + 2 * flow_q * c - 2 * x * d)

        c, d = zero, d_fixed
        for _ in range(MAX_SWEEPS):
            a, b = flows(c, d)
            new_c = (g_l + r * a + x * b + z2 * d) / sending
            new_d = d_fixed - self.strictly_below @ (current2 * new_c)
            moved = max(np.abs(new_c - c).max(initial=0.0), np.abs(new_d - d).max(initial=0.0))
            c, d = new_c, new_d
            if moved <= SWEEP_TOLERANCE * max(1.0, np.abs(c).max(initial=0.0), np.abs(d).max(initial=0.0)):
                break
        a, b = flows(c, d)
        line = self.network.line_to
        fed = line >= 0
        dp, dq = np.zeros((k, self.network.n_buses)), np.zeros((k, self.network.n_buses))
        dp[:, fed], dq[:, fed] = a[line[fed]].T, b[line[fed]].T
        return dp, dq
