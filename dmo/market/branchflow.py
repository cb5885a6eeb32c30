"""The AC power flow of a radial feeder as the exact branch-flow (DistFlow) equations, and its loss factors.

Baran and Wu (1989) write the AC power flow of a radial feeder without shunts line by line; for line l from bus i
to bus j, with P_l, Q_l the flows leaving i, U = V^2 and l_l = |I_l|^2:

    P_l = p_j + sum of P_m over the lines m leaving j + r_l l_l        Q_l likewise with q_j and x_l
    U_j = U_i - 2 (r_l P_l + x_l Q_l) + (r_l^2 + x_l^2) l_l             l_l = (P_l^2 + Q_l^2) / U_i

Dropping the l_l terms is LinDistFlow (``scenarios.network.Network.lindistflow``). ``BranchFlow.solve`` solves them
whole by sweeps: flows from the losses of the last sweep, voltages from the flows, losses from both, until the
losses no longer move (a few sweeps on a distribution feeder). Its losses' sensitivities to each bus's P and Q (the
marginal loss factors, exact to first order), and any limit's, come from the adjoint of the same equations, solved
exactly by elimination on the feeder's tree (``BranchFlow.adjoint``). Everything is sparse products, elementwise
arithmetic and sums in a fixed order: the same bits on any CPU (no BLAS). Pure: arrays in, arrays out.
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
    ``adjoint`` the sensitivities and marginal losses there."""

    def __init__(self, network: Network):
        self.network = network
        d = sp.csr_array(network.downstream)  # lines x buses: bus b is at or below line l
        self.D, self.DT = d, d.T.tocsr()
        self.below = d[:, network.child].tocsr()  # lines x lines: line m is at or below line l
        self.r, self.x = network.r_pu, network.x_pu
        self.z2 = self.r ** 2 + self.x ** 2
        self.u0 = network.v_substation ** 2
        # The tree depth by depth, for the adjoint's elimination: the lines renumbered by depth (``order``; line l is
        # ``place[l]``), each depth's lines grouped by their parent's place, so that a line's children are one run of
        # the next depth. Per depth: its slice, each line's parent's place (``parent``; 0 at depth 1, which has none),
        # and the runs of its lines that share a parent (where each starts in the slice, and that parent's place).
        n = network.n_lines
        depth = np.bincount(self.below.indices, minlength=n)  # the lines on each line's path, itself included
        up = network.line_to[network.parent]  # each line's parent line (-1 for a line leaving the substation)
        self.order, self.place, start = np.zeros(0, int), np.zeros(n, int), 0
        self.depths: list[tuple[slice, np.ndarray, np.ndarray, np.ndarray]] = []
        for level in range(1, depth.max(initial=0) + 1):
            lines = np.flatnonzero(depth == level)
            parent = np.where(up[lines] >= 0, self.place[up[lines]], 0)
            lines, parent = lines[np.argsort(parent, kind="stable")], np.sort(parent, kind="stable")
            self.place[lines] = start + np.arange(len(lines))
            self.order = np.concatenate([self.order, lines])
            runs = np.flatnonzero(np.diff(parent, prepend=-1) != 0)
            self.depths.append((slice(start, start + len(lines)), parent, runs, parent[runs]))
            start += len(lines)

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

    def upward(self):
        """The depths from the leaves up, each as its slice, with the depth below it (its slice, where each run of
        lines sharing a parent starts in it, and those parents' places; None at the deepest)."""
        below = (None, None, None)
        for here, _, runs, owners in self.depths[::-1]:
            yield (here, *below)
            below = (here, runs, owners)

    def adjoint(self, point: OperatingPoint) -> Adjoint:
        """The adjoint of the branch-flow equations at ``point`` (``Adjoint``), eliminated on the tree: what depends
        on the point alone, worked out once for every set of quantities whose sensitivities are then asked.

        With multipliers a, b (the flows' equations), c (the currents') and d (the voltages') per line l (from bus i),
        the adjoint of the equations of a quantity y = sum g_p P + g_q Q + g_l l + g_u U is

            a_l = a_parent + g_p + 2 P_l c_l - 2 r_l d_l          b_l likewise with g_q, Q_l and x_l
            U_i c_l = g_l + r_l a_l + x_l b_l + z_l^2 d_l         d_l = g_u + sum over l's children m of d_m - l_m c_m

        and dy/dp_j is a (dy/dq_j is b) of the line feeding bus j. Eliminated from the leaves up, a child's d_m -
        l_m c_m is affine in its parent's a_l, b_l: tau_m + phi_m a_l + psi_m b_l. With Phi, Psi the sums of phi, psi
        over l's children and G = g_u + the sum of their tau, l's four equations given its parent's a, b (A = a_parent
        + g_p, B = b_parent + g_q) solve in closed form:

            alpha = 1 / (1 + 2 (r Phi + x Psi))          beta = 2 alpha (P Phi + Q Psi)        S = G + Phi A + Psi B
            gamma = 1 / (U - 2 (r P + x Q) + z^2 beta)   c = gamma (g_l + r A + x B - z^2 alpha S)
            d = alpha S + beta c                          a = A + 2 P c - 2 r d                 b = B + 2 Q c - 2 x d

        so that phi_l, psi_l (and Phi, Psi, depth by depth up from the leaves) depend on the point alone, and tau_l
        on the quantities through G. Down from the root, each line's a, b are then its parent's times a 2 x 2 matrix,
        plus what its own G and g give. Exact (no iteration, no tolerance) and stable: the pivots 1/alpha and 1/gamma
        are 1 to within the losses and the line's receiving-end U to first order."""
        o, net = self.order, self.network
        r, x, z2 = self.r[o], self.x[o], self.z2[o]
        flow_p, flow_q, current2, sending = point.flow_p[o], point.flow_q[o], point.current2[o], point.u[net.parent][o]
        phi, psi, big_phi, big_psi, alpha, beta, gamma = (np.zeros(net.n_lines) for _ in range(7))
        for here, below, runs, owners in self.upward():
            if below is not None:  # the children's phi, psi, summed per parent
                big_phi[owners], big_psi[owners] = np.add.reduceat(phi[below], runs), np.add.reduceat(psi[below], runs)
            alpha[here] = 1.0 / (1.0 + 2 * (r[here] * big_phi[here] + x[here] * big_psi[here]))
            beta[here] = 2 * alpha[here] * (flow_p[here] * big_phi[here] + flow_q[here] * big_psi[here])
            gamma[here] = 1.0 / (sending[here] - 2 * (r[here] * flow_p[here] + x[here] * flow_q[here])
                                 + z2[here] * beta[here])
            by_c = (beta[here] - current2[here]) * gamma[here]  # what d - l c gains per unit of c's numerator
            phi[here] = alpha[here] * big_phi[here] + by_c * (r[here] - z2[here] * alpha[here] * big_phi[here])
            psi[here] = alpha[here] * big_psi[here] + by_c * (x[here] - z2[here] * alpha[here] * big_psi[here])
        c_g, c_a, c_b = -gamma * z2 * alpha, gamma * (r - z2 * alpha * big_phi), gamma * (x - z2 * alpha * big_psi)
        d_a, d_b = alpha * big_phi, alpha * big_psi  # d = alpha G + d_a g_p + d_b g_q + beta c (parent's a = b = 0)
        by_a, by_b = d_a + beta * c_a, d_b + beta * c_b  # d per unit of the parent's a, b
        return Adjoint(self, *(v[:, None] for v in (
            alpha + (beta - current2) * c_g, phi, psi, (beta - current2) * gamma, c_g, c_a, c_b, gamma,
            alpha, d_a, d_b, beta, 2 * flow_p, 2 * flow_q, 2 * r, 2 * x,
            1 + 2 * flow_p * c_a - 2 * r * by_a, 2 * flow_p * c_b - 2 * r * by_b,
            2 * flow_q * c_a - 2 * x * by_a, 1 + 2 * flow_q * c_b - 2 * x * by_b)))


@dataclass(frozen=True, eq=False)
class Adjoint:
    """The branch-flow equations' adjoint at an operating point, eliminated on the tree (``BranchFlow.adjoint``),
    its coefficients per line in the tree's order (lines x 1): a child's d - l c is ``omega`` G + ``phi`` g_p +
    ``psi`` g_q + ``lam`` g_l with its parent's a = b = 0 (``tau``), and phi, psi times its parent's a, b; with the
    parent's a = b = 0, c = ``c_g`` G + ``c_a`` g_p + ``c_b`` g_q + ``c_l`` g_l and d = ``d_g`` G + ``d_a`` g_p +
    ``d_b`` g_q + ``d_c`` c; ``p2``, ``q2``, ``r2``, ``x2``: 2 P, 2 Q, 2 r, 2 x; a line's a, b grow by ``m_aa``,
    ``m_ab`` (``m_ba``, ``m_bb``) times its parent's a, b."""

    flow: BranchFlow
    omega: np.ndarray
    phi: np.ndarray
    psi: np.ndarray
    lam: np.ndarray
    c_g: np.ndarray
    c_a: np.ndarray
    c_b: np.ndarray
    c_l: np.ndarray
    d_g: np.ndarray
    d_a: np.ndarray
    d_b: np.ndarray
    d_c: np.ndarray
    p2: np.ndarray
    q2: np.ndarray
    r2: np.ndarray
    x2: np.ndarray
    m_aa: np.ndarray
    m_ab: np.ndarray
    m_ba: np.ndarray
    m_bb: np.ndarray

    def loss_factors(self, **gradients: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per bus, d losses / d p_j and d losses / d q_j (MW per MW, per Mvar; 0 at the substation); then the
        sensitivities of k more quantities given as ``sensitivities`` takes them (none by default, k = 0), from the
        same passes. Each quantity's arithmetic is its own: the bits are those of separate calls."""
        n = self.flow.network.n_lines
        k = next((np.shape(g)[1] for g in gradients.values()), 0)
        losses = {"g_l": self.flow.r[:, None]}  # the losses are sum r l
        dp, dq = self.sensitivities(**{name: np.hstack([losses.get(name, np.zeros((n, 1))),
                                                        gradients.get(name, np.zeros((n, k)))])
                                       for name in ("g_p", "g_q", "g_l", "g_u")})
        return dp[0], dq[0], dp[1:], dq[1:]

    def sensitivities(self, g_p=None, g_q=None, g_l=None, g_u=None) -> tuple[np.ndarray, np.ndarray]:
        """The sensitivities of k quantities that are each linear in the lines' flows, currents and voltages, y =
        sum g_p P + g_q Q + g_l l + g_u U (each g, lines x k, 0 if not given; g_u's row l is the voltage at line l's
        child bus): dy/dp and dy/dq (k x buses, 0 at the substation), to first order. Two passes over the depths:
        up from the leaves, each line's G = g_u + its children's tau; down from the root, each line's a, b."""
        flow = self.flow
        n, o = flow.network.n_lines, flow.order
        k = next(np.shape(g)[1] for g in (g_p, g_q, g_l, g_u) if g is not None)
        g_p, g_q, g_l, g_u = (np.zeros((n, k)) if g is None else np.asarray(g, float)[o] for g in (g_p, g_q, g_l, g_u))
        own = self.phi * g_p + self.psi * g_q + self.lam * g_l  # tau less omega G
        big_g, tau = g_u.copy(), np.zeros((n, k))
        for here, below, runs, owners in flow.upward():
            if below is not None:
                big_g[owners] += np.add.reduceat(tau[below], runs, axis=0)
            tau[here] = self.omega[here] * big_g[here] + own[here]
        c = self.c_g * big_g + self.c_a * g_p + self.c_b * g_q + self.c_l * g_l
        d = self.d_g * big_g + self.d_a * g_p + self.d_b * g_q + self.d_c * c
        a, b = g_p + self.p2 * c - self.r2 * d, g_q + self.q2 * c - self.x2 * d  # with the parent's a = b = 0
        for here, parent, _, _ in flow.depths[1:]:
            parent_a, parent_b = a[parent], b[parent]
            a[here] += self.m_aa[here] * parent_a + self.m_ab[here] * parent_b
            b[here] += self.m_ba[here] * parent_a + self.m_bb[here] * parent_b
        line = flow.network.line_to
        fed = line >= 0
        dp, dq = np.zeros((k, flow.network.n_buses)), np.zeros((k, flow.network.n_buses))
        dp[:, fed], dq[:, fed] = a[flow.place[line[fed]]].T, b[flow.place[line[fed]]].T
        return dp, dq
