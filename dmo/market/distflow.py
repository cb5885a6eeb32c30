"""The DMO's day-ahead clearing on a radial feeder: welfare-maximising LinDistFlow with a price per bus (DLMPs).

Pure and deterministic, like ``clearing``: bids, a ``Network`` and each microgrid's bus in, a ``NetworkClearing``
out. The rules are stated in docs/market.md, "Clearing on a feeder". In short, per hour:

- If the copper plate's clearing (``clearing.clear_hour`` of the whole book, within the substation's limits less
  the fixed load) breaks no line limit and no voltage limit, it is the answer, bit for bit: one price everywhere.
- Otherwise an LP maximises welfare under LinDistFlow (Baran and Wu 1989) and the substation's limits, with load
  shedding at the value of lost load so that every hour clears. It is written in the buses' loads: LinDistFlow's
  balance and voltage-drop equations are solved in closed form (flows ``D p``, voltages ``U0 - R p - X q``), and
  the limits of lines and buses the solution respects are left out until a solution breaks them (constraint
  generation; a limit that holds has a zero dual, so the optimum and the prices are those of the whole LP).
- Prices come from the duals: the energy price at the substation, plus per bus a congestion and a voltage component,
  each the duals of the limits times the sensitivities of the flows and voltages to the bus's load. Awards are then
  decided from the prices at each bus, as ``clearing`` decides them from its one price: steps in the money in full,
  out of it not at all, steps exactly at the bus's price share pro rata what the LP leaves them at that bus.

Order independence is exact: the LP is built from a canonical order of the steps (bus, price, quantity, agent),
HiGHS is deterministic on a given LP, and the awards are summed per agent with ``math.fsum``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog

from messages.schemas import PRICE_CAP
from scenarios import exact
from scenarios.horizon import HOURS, finite
from scenarios.network import Network, voltage_band

from . import quadratic
from .branchflow import Adjoint, BranchFlow, OperatingPoint
from .clearing import (CLEARING_METHODS, FLAT, BidCurve, Book, IsoCurve, Segments,
                       clear_on_curve, hour_book, market_inputs, per_agent, segments)

# The value of lost load ($/MWh): what shedding a MW of fixed load costs the welfare. It is the bid cap, so no bid
# the DMO accepts outbids serving the fixed load.
VOLL = PRICE_CAP
# A line's thermal limit P^2 + Q^2 <= s^2 as the regular octagon inscribed in the circle with vertices on the axes:
# eight facets n_P P + n_Q Q <= s, t = tan(pi/8). With Q = 0 the limit on P is exactly s (docs/market.md).
_T = math.tan(math.pi / 8)
FACETS = np.array([(1, _T), (_T, 1), (-_T, 1), (-1, _T), (-1, -_T), (-_T, -1), (_T, -1), (1, -_T)])
# A limit holds within this (MW for lines, p.u.^2 for U = V^2); a looser one is added to the LP (HiGHS then meets it
# within its own feasibility tolerance, 1e-7).
LIMIT_TOLERANCE = 1e-9
# Limits added to the LP per round: the worst-broken facet of each of at most this many lines, and the worst-broken
# voltage limit of as many buses. Limits break together along a feeder (relieving the worst relieves many others), so
# a few rounds of a small LP beat one round of every broken limit: on a 1000-bus feeder with heavy load, 0.72 s for
# a day against 4.6 s, and 10 or 200 a round took 1.2 and 1.4 s (docs/benchmarks.md, "clearing").
LIMITS_PER_ROUND = 40
# A step is at its bus's price when the LP leaves it strictly part-accepted, or when the bus price from the duals
# lies within this of its bid price ($/MWh): floating-point duals then stand for the bid's own price.
PRICE_TOLERANCE = 1e-9
# Steps at their bus prices share alike at buses whose columns in the balance and the held limits agree to this many
# significant digits: LinDistFlow's equal columns are equal bits, the AC flow's sensitivities agree to about 1e-15.
SHARE_DIGITS = 12
# The AC-faithful clearing's iterations end when the AC flow of the plan keeps every bus within this of its voltage
# limits (p.u.) and every line within this share of its rating, or after MAX_AC_ITERATIONS linearised clearings.
AC_VOLTAGE_TOLERANCE = 1e-6
AC_LOADING_TOLERANCE = 1e-6
MAX_AC_ITERATIONS = 20
AC_CYCLE_TOLERANCE = 1e-9  # MW: a plan this close to the one two clearings before repeats it
# MW, Mvar: a plan this close to the operating point its LP was linearised at is that point (its loss factors and
# sensitivities are the plan's own: its prices differ from those of the LP linearised at the plan itself by at most
# 3.4e-4 $/MWh over `dmosim bench clearing`'s days on ieee33 and a 1000-bus feeder)
AC_PLAN_TOLERANCE = 1e-4
# $/MWh: the prices of an hour whose plans alternated support its settled awards within this (``_supported``)
AC_PRICE_TOLERANCE = 1e-3


@dataclass(frozen=True, eq=False)  # arrays inside: compare fields, not results
class NetworkClearing:
    """A market day cleared on a feeder. What ``clearing.ClearingResult`` has, with the same meaning: ``price`` (the
    substation's energy price per hour, $/MWh), ``awards`` (agent -> 24 MW, + import, sorted agents), ``congested``
    (per hour: "import", "export", "line", "voltage" or "none") and ``net_import(hour)``; and per agent
    ``agent_price`` (agent -> 24: its bus's price, at which it is awarded and settled).

    Per hour and bus (arrays 24 x buses, in ``network.buses`` order, read-only): ``bus_price`` = ``energy`` (24,
    broadcast) + ``congestion`` + ``voltage``, the price of a microgrid's exchange at the bus ($/MWh; at a power
    factor below 1, of its P with the Q it draws); ``voltage_pu``, ``shed_mw`` (fixed load shed) and ``spill_mw``
    (fixed generation spilled). Per hour and line (24 x lines):
    ``flow_p`` (MW) and ``flow_q`` (Mvar) away from the substation, and ``limit_loading``, the loading the clearing
    limits: the line's largest facet n_P P + n_Q Q over its rating (1 where a facet binds; |S| / rating is 0.92 to 1
    there, the octagon lying inside the circle).

    What binds, per hour (none in an hour the copper plate clears): ``binding_facet`` (24 x lines, int), the facet
    (0..7, ``FACETS``) of each line the hour's LP holds at its bound, -1 where none (of two at a vertex, the one with
    the larger dual), and ``line_shadow_price``, what a MW more of its rating would add to the welfare ($/h per MW,
    the sum of its facets' duals; 0 where none binds); ``binding_voltage`` (24 x buses, int), -1 where a bus's lower
    voltage limit binds, +1 its upper one, 0 neither, and ``voltage_shadow_price``, what 1 p.u. more room at that
    limit would add ($/h per p.u. of V, the dual of its U = V^2 limit times dU/dV = 2 V at the limit; 0 where none
    binds). ``lines_binding``, ``buses_binding``: per hour, the indices of those lines and buses.
    ``exchange_mw``: the substation's import from the ISO (fixed load + awards - shed + spilled).
    ``welfare`` ($ per hour): the accepted purchases' bid value less the sales' and the ISO's energy, the shed load
    at ``voll`` and the spilled generation at the spill price.

    ``method``: "lindistflow" (the state above is LinDistFlow's, ``loss`` is 0) or "ac" (cleared on LinDistFlow
    corrected at the AC flow of its own plan: ``loss``, 24 x buses, is each bus price's loss component, and the
    state is the AC flow's, flows at each line's substation end). ``iterations``: per hour, the corrected clearings
    it took (0 for "lindistflow"). Per hour, what the AC flow of the plan breaks (0 where it holds, NaN where it has
    no AC solution): ``ac_voltage_excess_pu``, the largest distance of a bus's AC voltage outside its limits (p.u.),
    and ``ac_overload``, the largest share of a rating by which a line's apparent power at its sending end exceeds it.
    """

    price: tuple[float, ...]
    awards: dict[str, tuple[float, ...]]
    congested: tuple[str, ...]
    agent_price: dict[str, tuple[float, ...]]
    bus_price: np.ndarray
    energy: np.ndarray
    congestion: np.ndarray
    voltage: np.ndarray
    binding_facet: np.ndarray
    line_shadow_price: np.ndarray
    binding_voltage: np.ndarray
    voltage_shadow_price: np.ndarray
    flow_p: np.ndarray
    flow_q: np.ndarray
    limit_loading: np.ndarray
    voltage_pu: np.ndarray
    shed_mw: np.ndarray
    spill_mw: np.ndarray
    exchange_mw: tuple[float, ...]
    welfare: tuple[float, ...]
    method: str
    loss: np.ndarray
    iterations: tuple[int, ...]
    ac_voltage_excess_pu: tuple[float, ...]
    ac_overload: tuple[float, ...]

    def net_import(self, hour: int) -> float:
        """The microgrids' net import in one hour: the sum of the awards (MW), as ``ClearingResult.net_import``."""
        return math.fsum(a[hour] for a in self.awards.values())

    @property
    def lines_binding(self) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(np.flatnonzero(row >= 0).tolist()) for row in self.binding_facet)

    @property
    def buses_binding(self) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(np.flatnonzero(row).tolist()) for row in self.binding_voltage)


@dataclass(frozen=True)
class HourProgram:
    """One hour's LP as the clearing solves it, whole: minimise ``c @ x`` subject to ``A_eq @ x == b_eq`` (the
    substation's balance), ``A_ub @ x <= b_ub`` (every line facet, then every bus's lower and upper voltage limit:
    ``rows`` names them) and ``lower <= x <= upper``. Columns: the book's steps in canonical order (signed MW),
    the shed load at ``shed_buses`` (MW), and the substation's import P0 (MW) as one column per segment of the ISO's
    curve (``clearing.segments``; one for the flat curve). ``x`` is the solution; the duals follow
    scipy's convention (d objective / d right-hand side): ``eq_dual`` (the energy price), ``ub_dual`` (<= 0; zero
    for a row the solution holds without it in the LP), ``lower_dual`` (>= 0), ``upper_dual`` (<= 0). ``objective``
    is minus the welfare (on an AC operating point, with its losses linearised there). ``exchange_eq`` (buses) and
    ``exchange_ub`` (rows x buses): the column a microgrid's MW at each bus has in the balance and in each limit
    (with its tan(phi) Mvar), as each step's column at its bus."""

    c: np.ndarray
    A_eq: np.ndarray
    b_eq: np.ndarray
    A_ub: np.ndarray
    b_ub: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    rows: tuple[str, ...]
    shed_buses: np.ndarray
    x: np.ndarray
    eq_dual: np.ndarray
    ub_dual: np.ndarray
    lower_dual: np.ndarray
    upper_dual: np.ndarray
    objective: float
    exchange_eq: np.ndarray
    exchange_ub: np.ndarray


@dataclass(frozen=True, eq=False)
class Linearised:
    """The feeder's AC flow linearised at an operating point (``Feeder.linearised``): ``values`` (one per limit,
    in ``Feeder.rows`` order), each limit's left side in the AC flow there; ``child_end`` (8 x lines), which end
    of its line each facet reads; ``lf_p``, ``lf_q`` (per bus) the losses' marginal factors. Each limit's
    sensitivities there come from ``adjoint`` (``branchflow.Adjoint.sensitivities``): the LP's limits are then the
    AC flow's to first order, exactly at the point. Those of the limits ``rows`` (in ``Feeder.grouped`` order), the
    first an hour's LP there holds, were solved with the loss factors: ``g_p``, ``g_q`` (rows x buses)."""

    point: OperatingPoint
    values: np.ndarray
    child_end: np.ndarray
    lf_p: np.ndarray
    lf_q: np.ndarray
    adjoint: Adjoint
    rows: np.ndarray
    g_p: np.ndarray
    g_q: np.ndarray


@dataclass(frozen=True, eq=False)
class Proximal:
    """A proximal term added to an hour's LP (``_Hour.solve``): (x - centre)' H (x - centre) / 2 over the steps
    ``steps`` (indices into the hour's book), at MW ``centre``, with H (steps x steps) positive semidefinite: the
    welfare a move of those steps from the centre loses to the curvature the LP's linearisation leaves out."""

    steps: np.ndarray
    hessian: np.ndarray
    centre: np.ndarray

    def objective(self, c: np.ndarray) -> tuple[np.ndarray, sp.sparray]:
        """The QP's linear term and Hessian for an LP of objective ``c`` (its first columns the book's steps)."""
        linear = c.copy()
        linear[self.steps] -= exact.matvec(self.hessian, self.centre)
        i, j = np.meshgrid(self.steps, self.steps, indexing="ij")
        return linear, sp.coo_array((self.hessian.ravel(), (i.ravel(), j.ravel())), shape=(len(c), len(c)))


# --- the feeder as sparse sensitivities ---------------------------------------------------------------------------

class Feeder:
    """A network's LinDistFlow sensitivities, sparse: flows P = D p and Q = D q (lines x buses), U = U0 - R p - X q
    with R = D' diag(2r) D and X = D' diag(2x) D (p.u. on 1 MVA), and its limits, the voltage band narrowed by
    ``margin`` p.u. at each end. Loads are per bus, MW and Mvar, + consumption."""

    def __init__(self, network: Network, margin: float = 0.0):
        self.network = network
        self.D = sp.csr_array(network.downstream)
        self.DT = self.D.T.tocsr()
        self.r2, self.x2 = 2 * network.r_pu, 2 * network.x_pu
        self.D_r = (sp.diags_array(self.r2) @ self.D).tocsr()  # R = D' D_r, X = D' D_x
        self.D_x = (sp.diags_array(self.x2) @ self.D).tocsr()
        self.s_max = np.asarray(network.s_max_mva, float)
        self.u0 = network.v_substation ** 2
        v_lo, v_hi = voltage_band(network, margin)
        self.u_min, self.u_max = v_lo ** 2, v_hi ** 2
        self.tan_phi = network.tan_phi
        self.feeder_buses = np.flatnonzero(np.arange(network.n_buses) != network.root)
        # Limits as row ids: line l's facet k is 8 l + k; bus j's lower voltage limit 8 L + 2 j, its upper + 1 (the
        # substation is held at v_substation: its limits are none of the LP's).
        base = 8 * network.n_lines
        voltage = base + 2 * np.repeat(self.feeder_buses, 2) + np.tile([0, 1], len(self.feeder_buses))
        self.rows = np.concatenate([np.arange(base), voltage])
        j = self.feeder_buses  # every limit's right side b (``limits``), in ``rows`` order, and what it is of
        self.bounds = np.concatenate([np.repeat(self.s_max, 8),
                                      np.column_stack([self.u0 - self.u_min[j], self.u_max[j] - self.u0]).ravel()])
        self.scale = np.concatenate([np.repeat(self.s_max, 8), np.column_stack([self.u_min[j], self.u_max[j]]).ravel()])
        self.ac = BranchFlow(network)

    def linearised(self, point: OperatingPoint, rows: np.ndarray) -> Linearised:
        """The feeder's limits and losses linearised at the AC operating point ``point`` (``Linearised``), the
        sensitivities of the limits ``rows`` (those the hour's first LP there holds) solved with the loss factors."""
        values, child_end = self.ac_left_sides(point)
        adjoint, rows = self.ac.adjoint(point), self.grouped(np.unique(rows))
        lf_p, lf_q, g_p, g_q = adjoint.loss_factors(**self.gradients(child_end, rows))
        return Linearised(point, values, child_end, lf_p, lf_q, adjoint, rows, g_p, g_q)

    def grouped(self, rows: np.ndarray) -> np.ndarray:
        """The limits ``rows`` in the order ``limits`` gives their left and right sides: the lines' facets first."""
        base = 8 * self.network.n_lines
        return np.concatenate([rows[rows < base], rows[rows >= base]])

    def gradients(self, child_end: np.ndarray, grouped: np.ndarray) -> dict[str, np.ndarray]:
        """The limits ``grouped`` as quantities of the branch flow (``branchflow.Adjoint.sensitivities``' g_p, g_q,
        g_l, g_u, lines x limits), each facet read at the end ``child_end`` gives it (``ac_left_sides``): facet n of
        line l is n_P P_l + n_Q Q_l, less n_P r_l l_l + n_Q x_l l_l at the child end; a bus's lower voltage limit
        is -U, its upper one U."""
        net, base = self.network, 8 * self.network.n_lines
        line, facet = divmod(grouped[grouped < base], 8)
        bus, upper = divmod(grouped[grouped >= base] - base, 2)
        gradient = {g: np.zeros((net.n_lines, len(grouped))) for g in ("g_p", "g_q", "g_l", "g_u")}
        facets = np.arange(len(line))
        n_p, n_q = FACETS[facet, 0], FACETS[facet, 1]
        gradient["g_p"][line, facets], gradient["g_q"][line, facets] = n_p, n_q
        gradient["g_l"][line, facets] = -np.where(child_end[facet, line], n_p * self.ac.r[line]
                                                  + n_q * self.ac.x[line], 0.0)
        gradient["g_u"][net.line_to[bus], len(line) + np.arange(len(bus))] = np.where(upper == 1, 1.0, -1.0)
        return gradient

    def ac_left_sides(self, point: OperatingPoint) -> tuple[np.ndarray, np.ndarray]:
        """Every limit's left side (as ``left_sides``) in the AC flow ``point``, and per line facet (8 x lines)
        whether it is taken at the line's child end: a line's facet n reads the flow at whichever end n P + n Q is
        larger (the end power enters, where the AC check reads a line's loading; the child end's flow is the parent
        end's less the line's losses, r l and x l)."""
        parent = FACETS[:, :1] * point.flow_p + FACETS[:, 1:] * point.flow_q  # 8 x lines
        lost = FACETS[:, :1] * (self.ac.r * point.current2) + FACETS[:, 1:] * (self.ac.x * point.current2)
        child_end = lost < 0
        drop = self.u0 - point.u[self.feeder_buses]
        facets = np.where(child_end, parent - lost, parent)
        return np.concatenate([facets.T.ravel(), np.column_stack([drop, -drop]).ravel()]), child_end

    def state(self, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Flows P, Q (lines) and U = V^2 (buses) for loads p, q (buses)."""
        flow_p, flow_q = self.D @ p, self.D @ q
        return flow_p, flow_q, self.u0 - self.drop(flow_p, flow_q)

    def drop(self, flow_p: np.ndarray, flow_q: np.ndarray) -> np.ndarray:
        """U0 - U at every bus for the line flows P, Q: R p + X q."""
        return self.DT @ (self.r2 * flow_p + self.x2 * flow_q)

    def left_sides(self, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Every limit's left side G_P p + G_Q q (``limits``) for loads p, q, in ``rows`` order: each line's eight
        facets n_P P + n_Q Q, then each bus's U0 - U (its lower voltage limit) and U - U0 (its upper one).
        ``bounds - left_sides(p, q)`` is every limit's slack."""
        flow_p, flow_q = self.D @ p, self.D @ q
        drop = self.drop(flow_p, flow_q)[self.feeder_buses]
        facets = FACETS[:, :1] * flow_p + FACETS[:, 1:] * flow_q  # 8 x lines
        return np.concatenate([facets.T.ravel(), np.column_stack([drop, -drop]).ravel()])

    def violated(self, p: np.ndarray, q: np.ndarray, near: OperatingPoint | None = None
                 ) -> tuple[np.ndarray, np.ndarray, OperatingPoint | None]:
        """The ids of the limits the loads p, q break by more than LIMIT_TOLERANCE, sorted, and by how much as a
        share of the limit (of s_max for a line facet, of U_min or U_max for a bus): in LinDistFlow, or, given an
        AC operating point ``near`` them, in the AC flow (every limit, if it has none). Third, the AC flow it solved
        (None without ``near``, or where it has none)."""
        point = None
        if near is not None:
            point = self.ac.solve(p, q, near)
            left = self.bounds + 1.0 if point is None else self.ac_left_sides(point)[0]
        else:
            left = self.left_sides(p, q)
        excess = left - self.bounds
        broken = excess > LIMIT_TOLERANCE
        return self.rows[broken], excess[broken] / self.scale[broken], point

    def worst(self, ids: np.ndarray, share: np.ndarray, most: int) -> np.ndarray:
        """Of the broken limits ``ids``, the worst facet of each line, then the ``most`` lines and the ``most``
        buses that break theirs by the largest share, sorted."""
        base = 8 * self.network.n_lines
        group = np.where(ids < base, ids // 8, ids // 2 + base)  # a line's facets, a bus's two limits
        order = np.lexsort((ids, -share, group))
        first = order[np.unique(group[order], return_index=True)[1]]  # the worst of each line and of each bus
        picked = []
        for kind in (ids[first] < base, ids[first] >= base):
            mine = first[kind]
            picked.append(ids[mine[np.lexsort((ids[mine], -share[mine]))[:most]]])
        return np.sort(np.concatenate(picked))

    def behind(self, rows: np.ndarray) -> np.ndarray:
        """Per bus, whether a microgrid's exchange there (P, with tan(phi) P of Q) moves any of the limits ``rows``:
        a line's facet n moves with the buses below the line (unless n_P + tan(phi) n_Q = 0), a bus's voltage with
        the buses below each line of its path whose r + tan(phi) x is not 0 (their R + tan(phi) X is not 0)."""
        base = 8 * self.network.n_lines
        line, facet = divmod(rows[rows < base], 8)
        moved = np.zeros(self.network.n_lines)
        moved[line[FACETS[facet] @ (1.0, self.tan_phi) != 0]] = 1.0
        paths = np.zeros(self.network.n_buses)
        paths[(rows[rows >= base] - base) // 2] = 1.0
        moved[(self.D @ paths > 0) & (self.r2 + self.tan_phi * self.x2 > 0)] = 1.0
        return self.DT @ moved > 0

    def limits(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The limits ``rows`` as G_P p + G_Q q <= b over the buses' loads (dense rows x buses: a voltage limit's
        row is dense anyway): a facet n of line l is n_P D_l, n_Q D_l <= s_l; a lower voltage limit R_j, X_j <= U0 -
        U_min_j (U_j >= U_min_j); an upper one -R_j, -X_j <= U_max_j - U0."""
        base = 8 * self.network.n_lines
        line, facet = divmod(rows[rows < base], 8)
        bus, upper = divmod(rows[rows >= base] - base, 2)
        sign = np.where(upper == 1, -1.0, 1.0)[:, None]
        d = self.network.downstream[line]
        path = self.DT[bus]  # the lines from the substation to each bus
        g_p = np.vstack([FACETS[facet, :1] * d, sign * (path @ self.D_r).toarray()])
        g_q = np.vstack([FACETS[facet, 1:] * d, sign * (path @ self.D_x).toarray()])
        return g_p, g_q, self.bounds[np.searchsorted(self.rows, self.grouped(rows))]

    def loading(self, left: np.ndarray) -> np.ndarray:
        """Per line, its largest facet over its rating, from every limit's left side ``left`` (``left_sides`` or
        ``ac_left_sides``): the loading the clearing limits, 1 at a binding facet."""
        return left[:8 * self.network.n_lines].reshape(-1, 8).max(axis=1) / self.s_max

    def binding(self, held: np.ndarray, relief: np.ndarray) -> tuple[np.ndarray, ...]:
        """The limits ``held`` at their bounds (ids, sorted) with their duals as ``relief`` (>= 0) per line and bus:
        the facet of each line (-1: none; the one with the larger dual), the sum of its facets' duals, the voltage
        limit of each bus (-1 lower, +1 upper, 0 none) and its dual per p.u. of V (the U = V^2 dual times 2 V at the
        limit), as ``NetworkClearing`` has them."""
        net, base = self.network, 8 * self.network.n_lines
        facet, line_shadow = np.full(net.n_lines, -1), np.zeros(net.n_lines)
        on_line = held < base
        line, k = divmod(held[on_line], 8)
        np.add.at(line_shadow, line, relief[on_line])
        first = np.lexsort((k, -relief[on_line], line))
        first = first[np.unique(line[first], return_index=True)[1]]
        facet[line[first]] = k[first]
        bus, upper = divmod(held[~on_line] - base, 2)
        side, voltage_shadow = np.zeros(net.n_buses, int), np.zeros(net.n_buses)
        side[bus] = np.where(upper == 1, 1, -1)
        limit = np.where(upper == 1, self.u_max[bus], self.u_min[bus])
        voltage_shadow[bus] = relief[~on_line] * 2.0 * np.sqrt(limit)
        return facet, line_shadow, side, voltage_shadow

    def row_names(self, rows: np.ndarray) -> tuple[str, ...]:
        net, base = self.network, 8 * self.network.n_lines
        return tuple(f"line {net.buses[net.parent[r // 8]]}-{net.buses[net.child[r // 8]]} facet {r % 8}" if r < base
                     else f"bus {net.buses[(r - base) // 2]} {'v_max' if (r - base) % 2 else 'v_min'}" for r in rows)


# --- one hour -----------------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Hour:
    """One hour's inputs on the feeder: the book in canonical order with each step's bus, the fixed loads, the
    ISO's curve within the substation's limits and the value of lost load."""

    feeder: Feeder
    book: Book
    bus: np.ndarray
    fixed_p: np.ndarray
    fixed_q: np.ndarray
    curve: Segments
    voll: float
    spill_price: float = 0.0  # $/MWh: what spilling a MW of fixed generation costs the welfare
    at: Linearised | None = None  # the AC operating point the hour's LP is corrected at (None: LinDistFlow alone)
    # per step, the MW its award is held at (NaN: free; None: none held): the steps a proximal clearing settled
    # (``_settle``), which the LP leaves at their prices and the awards keep where the plan has them
    pinned: np.ndarray | None = None

    @property
    def shed_buses(self) -> np.ndarray:
        """Buses whose fixed injection can be curtailed: those consuming P (their load shed, its Q in proportion)
        and those producing it (their generation spilled, P alone)."""
        j = self.feeder.feeder_buses
        return j[self.fixed_p[j] != 0]

    @property
    def shed_sign(self) -> np.ndarray:
        """Per bus, how a MW curtailed there moves its net load: -1 where load is shed, +1 where generation is
        spilled."""
        return np.where(self.fixed_p > 0, -1.0, 1.0)

    def shed_cost(self, buses: np.ndarray) -> np.ndarray:
        """What a MW curtailed at each of ``buses`` costs the welfare: VOLL for load, the spill price for
        generation."""
        return np.where(self.fixed_p[buses] > 0, self.voll, self.spill_price)

    def loads(self, step_mw: np.ndarray, shed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per bus, P and Q consumed: fixed load + the steps' net import (Q = tan(phi) P), less the load shed and
        plus the generation spilled (``shed``, MW curtailed per bus; Q in proportion)."""
        n = len(self.fixed_p)
        inject = np.bincount(self.bus, step_mw, minlength=n)
        moved = self.shed_sign * shed
        return (self.fixed_p + inject + moved, self.fixed_q + self.feeder.tan_phi * inject + self.shed_ratio * moved)

    @property
    def shed_ratio(self) -> np.ndarray:
        """Per bus, the Q shed with each MW of its fixed load (its ratio Q/P; 0 where it consumes no P: a spilled
        generation gives up its P alone, its Q stays)."""
        n = len(self.fixed_p)
        return np.divide(self.fixed_q, self.fixed_p, out=np.zeros(n), where=self.fixed_p > 0)

    def limits(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``Feeder.limits``; at an AC operating point, the limits of the AC flow linearised there instead: left
        sides G_P p + G_Q q with G the AC flow's sensitivities, right sides b - y(point) + G_P p* + G_Q q* for each
        limit's AC left side y at the point's loads p*, q*, less the fixed loads' G_P p_f + G_Q q_f, which
        ``program`` takes off LinDistFlow's right sides (here in one sum with the point's loads: p* - p_f is
        nonzero only where microgrids or shed loads are)."""
        feeder = self.feeder
        if self.at is None:
            return feeder.limits(rows)
        at, grouped = self.at, feeder.grouped(rows)
        if np.array_equal(grouped, at.rows):  # the limits the linearisation solved with the loss factors
            g_p, g_q = at.g_p, at.g_q
        else:
            g_p, g_q = at.adjoint.sensitivities(**feeder.gradients(at.child_end, grouped))
        where = np.searchsorted(feeder.rows, grouped)
        b = (feeder.bounds[where] - at.values[where] + exact.matvec(g_p, at.point.p - self.fixed_p)
             + exact.matvec(g_q, at.point.q - self.fixed_q))
        return g_p, g_q, b

    def gain(self, q_per_p: np.ndarray | float, buses: np.ndarray) -> np.ndarray:
        """What a MW more load at each of ``buses`` (with ``q_per_p`` Mvar) draws at the substation: 1, plus its
        marginal losses at the hour's operating point (LinDistFlow alone: 1)."""
        if self.at is None:
            return np.ones(len(buses))
        return 1.0 + self.at.lf_p[buses] + q_per_p * self.at.lf_q[buses]

    def balance(self) -> float:
        """The substation's balance's right side: the fixed load, and at an operating point the losses there less
        what the loss factors already count of the fixed load's distance from it."""
        if self.at is None:
            return math.fsum(self.fixed_p)
        point, at = self.at.point, self.at
        return math.fsum(np.concatenate([self.fixed_p, [point.losses], at.lf_p * (self.fixed_p - point.p),
                                         at.lf_q * (self.fixed_q - point.q)]))

    def program(self, g_p: np.ndarray, g_q: np.ndarray, b: np.ndarray, shed_at: np.ndarray) -> tuple[np.ndarray, ...]:
        """The LP over the steps, the shed loads at ``shed_at`` and P0's segments, with the limits G_P p + G_Q q <= b:
        c, A_eq, b_eq, A_ub, b_ub, lower, upper (dense)."""
        book, curve = self.book, self.curve
        n = len(curve.price)
        # A step's MW raises its bus's P by 1 and Q by tan(phi); a shed MW of load lowers P by 1 and Q by the
        # load's ratio, a spilled MW of generation raises them so.
        sign = self.shed_sign[shed_at]
        a_ub = np.hstack([(g_p + self.feeder.tan_phi * g_q)[:, self.bus], sign * self.shed_columns(g_p, g_q, shed_at),
                          np.zeros((len(b), n))])
        b_ub = b if self.at is not None else b - exact.matvec(g_p, self.fixed_p) - exact.matvec(g_q, self.fixed_q)
        k = len(shed_at)
        # The substation's balance: P0 = fixed load + net import of the steps - shed (LinDistFlow is lossless; at an
        # AC operating point, each MW with its marginal losses, and the losses there), P0 the sum of its segments'
        # columns, each from 0 outwards (its prices rise with P0: the LP fills them in order)
        a_eq = np.concatenate([-self.gain(self.feeder.tan_phi, self.bus),
                               -sign * self.gain(self.shed_ratio[shed_at], shed_at), np.ones(n)])[None, :]
        b_eq = np.array([self.balance()])
        c = np.concatenate([-book.price, self.shed_cost(shed_at), curve.price])
        lower = np.concatenate([np.minimum(book.quantity, 0.0), np.zeros(k),
                                np.minimum(curve.low, 0.0) - np.minimum(curve.high, 0.0)])
        upper = np.concatenate([np.maximum(book.quantity, 0.0), np.abs(self.fixed_p[shed_at]),
                                np.maximum(curve.high, 0.0) - np.maximum(curve.low, 0.0)])
        return c, a_eq, b_eq, a_ub, b_ub, lower, upper

    def shed_columns(self, g_p: np.ndarray, g_q: np.ndarray, shed_at: np.ndarray) -> np.ndarray:
        """The limits' left sides for a MW more of load at each bus of ``shed_at``, with Q in its fixed load's or
        generation's proportion."""
        return g_p[:, shed_at] + g_q[:, shed_at] * self.shed_ratio[shed_at]

    def solve(self, rows: np.ndarray, proximal: Proximal | None = None) -> _Solution:
        """Solve with the limits ``rows`` and no curtailment; add the limits the solution breaks (the worst,
        ``worst``) and the fixed loads and generation whose curtailment gains welfare at the solution's prices (a
        load whose bus price exceeds VOLL, a generation whose bus price is below minus the spill price: their
        columns' reduced costs are negative), again until neither is left: then the solution is that of the LP with
        every limit and every curtailment. With ``proximal``, the LP's objective gains its quadratic term (a QP)."""
        rows = np.asarray(rows, int)
        g_p, g_q, b = self.limits(rows)
        shed_at, every = np.zeros(0, int), self.shed_buses
        while True:
            lp = self.program(g_p, g_q, b, shed_at)
            c, a_eq, b_eq, a_ub, b_ub, lower, upper = lp
            if proximal is not None:
                res = quadratic.minimise(*proximal.objective(c), a_eq, b_eq, a_ub, b_ub, lower, upper)
            else:
                res = linprog(c, A_ub=a_ub if len(b) else None, b_ub=b_ub if len(b) else None, A_eq=a_eq,
                              b_eq=b_eq, bounds=np.column_stack([lower, upper]), method="highs",
                              options={"presolve": False})
            if res.status == 2 and len(shed_at) < len(every):  # infeasible without curtailing: offer every one
                shed_at = every
                continue
            if res.status != 0:  # only if a limit excludes even the unloaded feeder (e.g. v_min above v_substation)
                message = " ".join(str(res.message).split())
                raise ValueError(f"network {self.feeder.network.name}: the hour cannot clear even with every fixed "
                                 f"load shed and every generation spilled ({message})")
            solution = _Solution(rows, g_p, g_q, b, shed_at, len(self.curve.price), lp, res)
            reduced = self.shed_cost(every) + self.shed_sign[every] * self.shed_value(solution, every)
            dear = np.setdiff1d(every[reduced < -PRICE_TOLERANCE], shed_at)
            if dear.size:
                shed_at = np.union1d(shed_at, dear)
                continue
            ids, share, flow = self.feeder.violated(*self.loads(solution.step_mw, solution.shed(len(self.fixed_p))),
                                                    None if self.at is None else self.at.point)
            new = ~np.isin(ids, rows)
            if not new.any():
                return dataclasses.replace(solution, flow=flow)
            added = self.feeder.worst(ids[new], share[new], LIMITS_PER_ROUND)
            more = self.limits(added)
            rows = np.concatenate([rows, added])
            g_p, g_q, b = np.vstack([g_p, more[0]]), np.vstack([g_q, more[1]]), np.concatenate([b, more[2]])

    def shed_value(self, solution: _Solution, buses: np.ndarray) -> np.ndarray:
        """What a MW more of load at each of ``buses`` (with its fixed injection's Q) costs at the solution's duals:
        the energy price plus the limits' duals times its sensitivities. A load shed there saves it; a generation
        spilled there pays it."""
        relief = -solution.ub_dual
        columns = self.shed_columns(solution.g_p, solution.g_q, buses)
        energy = solution.res.eqlin.marginals[0] * self.gain(self.shed_ratio[buses], buses)
        return energy + exact.matvec(columns.T, relief)


@dataclass(frozen=True)
class _Solution:
    """An hour's LP as last solved: its limits (ids; left sides G_P, G_Q per bus; right sides b), the buses whose
    load it may shed, how many segments P0 has, its data (c, A_eq, b_eq, A_ub, b_ub, lower, upper) and scipy's
    result; at an AC operating point, ``flow``, the AC flow of its plan that constraint generation solved (None
    where it has none, and on LinDistFlow)."""

    rows: np.ndarray
    g_p: np.ndarray
    g_q: np.ndarray
    b: np.ndarray
    shed_at: np.ndarray
    segments: int
    lp: tuple[np.ndarray, ...]
    res: object
    flow: OperatingPoint | None = None

    @property
    def step_mw(self) -> np.ndarray:
        return self.res.x[:-self.segments - len(self.shed_at)]

    @property
    def p0_segments(self) -> np.ndarray:
        return self.res.x[-self.segments:]

    @property
    def p0(self) -> float:
        return math.fsum(self.p0_segments)

    def shed(self, n_buses: int) -> np.ndarray:
        out = np.zeros(n_buses)
        out[self.shed_at] = np.maximum(self.res.x[-self.segments - len(self.shed_at):-self.segments], 0.0)
        return out

    @property
    def ub_dual(self) -> np.ndarray:
        return self.res.ineqlin.marginals if len(self.b) else np.zeros(0)


@dataclass(frozen=True)
class _Cleared:
    """One hour's outcome: the energy price, the label, the steps' awards, the shed load, the bus prices with
    their components, the limits its LP held at their bounds (ids) with their duals as relief (>= 0), and the AC
    flow of its plan where the clearing solved it (``_Solution.flow``)."""

    energy: float
    congested: str
    step_mw: np.ndarray
    shed: np.ndarray
    bus_price: np.ndarray
    loss: np.ndarray
    congestion: np.ndarray
    voltage: np.ndarray
    held: np.ndarray
    relief: np.ndarray
    rows: np.ndarray  # the limits its LP had (none on the copper plate)
    flow: OperatingPoint | None = None


@dataclass(frozen=True)
class _Plan:
    """An hour's LP as solved, its own plan taken as it stands: no prices worked out, no awards decided from them
    (``_awarded`` does both). What an AC-faithful clearing linearises at until a plan is its own operating point."""

    solution: _Solution
    shed: np.ndarray

    @property
    def step_mw(self) -> np.ndarray:
        return self.solution.step_mw

    @property
    def rows(self) -> np.ndarray:
        return self.solution.rows

    @property
    def flow(self) -> OperatingPoint | None:
        return self.solution.flow

    @property
    def energy(self) -> float:
        """The energy price from the LP's duals."""
        return float(self.solution.res.eqlin.marginals[0])


def _plate(hour: _Hour) -> _Cleared | None:
    """The copper plate's clearing of the hour as a plan on the feeder (one price everywhere, nothing curtailed),
    with ``rows`` the worst of the LinDistFlow limits its awards break (none if they break none); None where the
    substation's limits leave the fixed load no room."""
    fixed = math.fsum(hour.fixed_p)
    if not hour.curve.bottom <= fixed <= hour.curve.top:
        return None
    price, congested, step_mw = clear_on_curve(hour.book, hour.curve, fixed)
    n = len(hour.fixed_p)
    ids, share, _ = hour.feeder.violated(*hour.loads(step_mw, np.zeros(n)))
    rows = hour.feeder.worst(ids, share, LIMITS_PER_ROUND) if ids.size else np.zeros(0, int)
    zero, none = np.zeros(n), np.zeros(0, int)
    return _Cleared(price, congested, step_mw, zero, np.full(n, price), zero, zero, zero, none, np.zeros(0), rows)


def _copper_plate(hour: _Hour) -> tuple[_Cleared | None, np.ndarray]:
    """The copper plate's clearing when it is this hour's answer (None otherwise), and the limits its awards
    break. It applies while the substation's limits leave room for the fixed load and its price is within VOLL
    (above it, shedding fixed load for the bids would gain welfare) and, on a feeder with fixed generation, at least
    minus the spill price (below it, spilling generation would), and never at an AC operating point (its losses are
    priced)."""
    plate = None if hour.at is not None else _plate(hour)
    if plate is None or plate.energy > hour.voll or (plate.energy < -hour.spill_price and (hour.fixed_p < 0).any()):
        return None, np.zeros(0, int)
    if plate.rows.size:
        return None, plate.rows
    return dataclasses.replace(plate, rows=np.zeros(0, int)), plate.rows


def _prices(hour: _Hour, sol: _Solution) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """The energy price and each bus's loss, congestion and voltage components from the duals: the energy price
    times the marginal losses of a microgrid's MW at the bus (P, with tan(phi) Mvar; 0 without an AC operating
    point), and each limit's dual times the sensitivity of its left side to that MW."""
    energy = sol.res.eqlin.marginals[0] + 0.0
    curve, x = hour.curve, sol.p0_segments
    *_, lower, upper = sol.lp
    inside = np.flatnonzero((lower[-len(x):] + LIMIT_TOLERANCE < x) & (x < upper[-len(x):] - LIMIT_TOLERANCE))
    if inside.size:
        energy = float(curve.price[inside[0]])  # a segment within its bounds: its reduced cost is zero exactly
    else:  # at a bound, the price the duals give within PRICE_TOLERANCE of the ISO's or a bid's is that price
        candidates = np.append(hour.book.price, curve.price)
        gap = np.abs(candidates - energy)
        if gap.min() <= PRICE_TOLERANCE:
            energy = float(candidates[np.lexsort((candidates, gap))[0]])
    relief = -sol.ub_dual  # >= 0: the welfare one unit of relief of the limit is worth
    g_mg = sol.g_p + hour.feeder.tan_phi * sol.g_q
    is_line = sol.rows < 8 * hour.feeder.network.n_lines
    every = np.arange(len(hour.fixed_p))
    loss = energy * (hour.gain(hour.feeder.tan_phi, every) - 1.0)
    return (energy, loss, exact.matvec(g_mg[is_line].T, relief[is_line]),
            exact.matvec(g_mg[~is_line].T, relief[~is_line]))


def _snap(hour: _Hour, step_mw: np.ndarray, bus_price: np.ndarray) -> np.ndarray:
    """Bus prices with each bus that has a step at its price set to that step's bid price exactly: the step the
    LP leaves part-accepted (in exact arithmetic its bid price is the bus's price), else the step whose price the
    duals' bus price meets within PRICE_TOLERANCE; nearest first."""
    book, bus = hour.book, hour.bus
    q = book.quantity
    inside = (np.abs(step_mw) > LIMIT_TOLERANCE) & (np.abs(q - step_mw) > LIMIT_TOLERANCE)
    gap = np.abs(book.price - bus_price[bus])
    at = inside | (gap <= PRICE_TOLERANCE)
    if not at.any():
        return bus_price
    i = np.flatnonzero(at)
    i = i[np.lexsort((book.price[i], gap[i], ~inside[i], bus[i]))]
    first = i[np.unique(bus[i], return_index=True)[1]]
    out = bus_price.copy()
    out[bus[first]] = book.price[first]
    return out


def _shared(hour: _Hour, sol: _Solution, bus_price: np.ndarray,
            held: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, OperatingPoint | None]:
    """The steps' awards, the curtailments and P0 decided from the bus prices (docs/market.md, "Awards from the
    prices"): a step in the money at its bus's price is accepted in full, one out of it not at all, and the steps at
    exactly their bus's price share, among the LP's optimal solutions (those that keep its duals' complementary
    slackness: every limit with a nonzero dual at its bound, every column with a nonzero reduced cost at its
    bound), the one that trades the most of them, each class of them accepted in equal shares: purchases alike,
    sales alike, at buses whose columns in the balance and in every limit held at its bound (``held``, per LP row)
    are equal (to SHARE_DIGITS significant digits), which no optimal solution can tell apart. Limits the LP left
    out are added while the shares break them. The prices are the LP's, whatever the shares. Also the AC flow of
    the loads it checked last, where it solved one (``_Solution.flow``: the LP's own plan's)."""
    book, bus = hour.book, hour.bus
    q, price = book.quantity, bus_price[bus]
    pinned = np.zeros(len(q), bool) if hour.pinned is None else np.isfinite(hour.pinned)
    at = (book.price == price) & ~pinned
    decided = np.where(np.where(q > 0, book.price > price, book.price < price), q, 0.0)
    if pinned.any():  # a step held at its MW (``_settle``) stays there
        decided = np.where(pinned, hour.pinned, decided)
    n_buses = len(hour.fixed_p)
    if not at.any():
        return decided, sol.shed(n_buses), sol.p0, sol.flow
    c, a_eq, b_eq, a_ub, b_ub, lower, upper = sol.lp
    x, s = sol.res.x, len(q)
    free = (np.abs(sol.res.lower.marginals) <= PRICE_TOLERANCE) & (np.abs(sol.res.upper.marginals) <= PRICE_TOLERANCE)
    tight = -sol.ub_dual > PRICE_TOLERANCE  # limits the duals hold at their bounds
    mine = np.flatnonzero(at)
    klass = _alike(np.vstack([a_eq, a_ub[held]]), mine, book)
    m = int(klass.max()) + 1
    onto = np.zeros((len(mine), m))
    onto[np.arange(len(mine)), klass] = q[mine]  # a class's column: its steps' columns times their quantities
    rest = np.arange(s, len(c))  # curtailments and P0's segments: free where their reduced cost is zero
    fixed = np.flatnonzero(decided)

    def split(a: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows over the classes' shares and the other columns, the decided steps' MW on the right side."""
        return np.hstack([a[:, mine] @ onto, a[:, rest]]), rhs - exact.matvec(a[:, fixed], decided[fixed])

    eq_a, eq_b = split(np.vstack([a_eq, a_ub[tight]]), np.concatenate([b_eq, b_ub[tight]]))
    ub_a, ub_b = split(a_ub[~tight], b_ub[~tight])
    bounds = np.column_stack([np.concatenate([np.zeros(m), np.where(free[rest], lower[rest], x[rest])]),
                              np.concatenate([np.ones(m), np.where(free[rest], upper[rest], x[rest])])])
    volume = np.concatenate([-np.abs(onto).sum(axis=0), np.zeros(len(rest))])  # the most MW of them traded
    rows = sol.rows
    while True:
        res = linprog(volume, A_ub=ub_a if len(ub_b) else None, b_ub=ub_b if len(ub_b) else None, A_eq=eq_a,
                      b_eq=eq_b, bounds=bounds, method="highs", options={"presolve": False})
        if res.status != 0:  # the LP's own solution: sharing it out per class could break a limit it does not hold
            return sol.step_mw.copy(), sol.shed(n_buses), sol.p0, sol.flow
        step_mw = decided.copy()
        step_mw[mine] = q[mine] * res.x[klass]
        shed = np.zeros(n_buses)
        shed[sol.shed_at] = np.maximum(res.x[m:m + len(sol.shed_at)], 0.0)
        ids, share, flow = hour.feeder.violated(*hour.loads(step_mw, shed),
                                                None if hour.at is None else hour.at.point)
        new = ~np.isin(ids, rows)
        if not new.any():
            return step_mw, shed, math.fsum(res.x[m + len(sol.shed_at):]), flow
        added = hour.feeder.worst(ids[new], share[new], LIMITS_PER_ROUND)
        rows = np.concatenate([rows, added])
        _, _, _, more_a, more_b, _, _ = hour.program(*hour.limits(added), sol.shed_at)
        more_a, more_b = split(more_a, more_b)
        ub_a, ub_b = np.vstack([ub_a, more_a]), np.concatenate([ub_b, more_b])


def _alike(columns: np.ndarray, mine: np.ndarray, book: Book) -> np.ndarray:
    """The class of each step of ``mine`` (indices into the book), numbered from 0: steps alike are purchases alike
    or sales alike, at one price, whose ``columns`` (rows x steps: the balance and the limits) are equal to
    SHARE_DIGITS significant digits, which no solution of the LP can tell apart."""
    signature = _significant(columns[:, mine].T, SHARE_DIGITS)
    key = np.column_stack([signature, book.quantity[mine] > 0, book.price[mine]])
    return np.unique(key, axis=0, return_inverse=True)[1].ravel()


def _equal_shares(mw: np.ndarray, klass: np.ndarray, quantity: np.ndarray) -> np.ndarray:
    """The MW ``mw`` of steps of ``quantity`` shared equally within each class ``klass``: each step the same share
    of its quantity as its class as a whole."""
    total, size = np.zeros(klass.max(initial=-1) + 1), np.zeros(klass.max(initial=-1) + 1)
    np.add.at(total, klass, mw)
    np.add.at(size, klass, quantity)
    return quantity * total[klass] / size[klass]


def _significant(a: np.ndarray, digits: int) -> np.ndarray:
    """``a`` rounded to ``digits`` significant digits (0 stays 0)."""
    magnitude = np.floor(np.log10(np.abs(a), out=np.zeros_like(a), where=a != 0))
    scale = 10.0 ** (digits - 1 - magnitude)
    return np.round(a * scale) / scale


def _on_feeder(hour: _Hour, rows: np.ndarray = np.zeros(0, int), priced: bool = True) -> _Cleared | _Plan:
    """Clear one hour: the copper plate where it holds, else the LP and prices per bus, its limits found from
    ``rows`` on (those of a clearing of the same hour at another operating point: most hold again); with
    ``priced=False``, the LP's own plan alone (``_Plan``)."""
    cleared, broken = _copper_plate(hour)
    if cleared is not None:
        return cleared
    sol = hour.solve(np.union1d(broken, rows))
    return _awarded(hour, sol) if priced else _Plan(sol, sol.shed(len(hour.fixed_p)))


def _awarded(hour: _Hour, sol: _Solution) -> _Cleared:
    """The hour's outcome from its LP ``sol``: the prices from its duals and the awards from the prices, the steps
    at their bus prices shared by the rule (``_shared``)."""
    energy, loss, congestion, voltage = _prices(hour, sol)
    x = sol.res.x
    if hour.pinned is not None:  # a settled hour: its plan holds the steps the LP may leave elsewhere on its face
        x = x.copy()
        x[:len(hour.pinned)] = np.where(np.isfinite(hour.pinned), hour.pinned, sol.step_mw)
    raw = energy + loss + congestion + voltage
    bus_price = _snap(hour, x[:len(hour.book.price)], raw)
    if hour.pinned is not None:  # the loss components at the plan itself, which its awards meet
        loss = np.where(bus_price == raw, loss, bus_price - energy - congestion - voltage)
    _, _, _, a_ub, b_ub, _, _ = sol.lp
    at_bound = b_ub - exact.matvec(a_ub, x) <= LIMIT_TOLERANCE * np.maximum(1.0, np.abs(b_ub))
    step_mw, shed, p0, flow = _shared(hour, sol, bus_price, at_bound)
    order = np.argsort(sol.rows[at_bound], kind="stable")
    held, relief = sol.rows[at_bound][order], (-sol.ub_dual[at_bound] + 0.0)[order]
    lines = held < 8 * hour.feeder.network.n_lines
    if p0 >= hour.curve.top - LIMIT_TOLERANCE:
        congested = "import"
    elif p0 <= hour.curve.bottom + LIMIT_TOLERANCE:
        congested = "export"
    else:
        congested = "line" if lines.any() else "voltage" if held.size else "none"
    return _Cleared(energy, congested, step_mw, shed, bus_price, loss, congestion, voltage, held, relief, sol.rows,
                    flow)


def _ac_faithful(hour: _Hour) -> tuple[_Hour, _Cleared, OperatingPoint | None, int]:
    """Clear one hour on the AC flow linearised at its own plan (docs/market.md, "AC-faithful clearing"): clear on
    LinDistFlow, solve the branch-flow equations at the plan, clear again on the AC flow linearised at that
    operating point (its limits' sensitivities and marginal losses there), until the AC flow of the plan keeps
    every voltage within AC_VOLTAGE_TOLERANCE p.u. and every line within AC_LOADING_TOLERANCE of its rating, at most
    MAX_AC_ITERATIONS linearised clearings. Where the first plan has no AC solution (the copper plate's, then
    LinDistFlow's), or no plan meets the first linearisation's limits even curtailing every fixed injection (a
    reactive load that cannot be shed, its line full in AC), the hour is LinDistFlow's clearing, and what its AC
    flow breaks is reported; where a later one fails so, the last plan that did not.

    The clearings linearise at their LPs' own plans; once a plan is its own operating point, its awards are shared
    by the rule (``_awarded``), and if that moves the plan, the clearings go on sharing theirs.

    Plans can alternate: a step whose own losses move its bus's price across its bid is in at one operating point
    and out at the other, and each plan's AC flow is a little off the other's linearisation. Once a plan repeats
    the one two clearings before, the hour is settled between the two (``_settle``); where that finds no plan
    within MAX_AC_ITERATIONS, the clearing keeps the one of the two whose AC flow breaks the limits least: its
    prices and awards are those of its own LP, and what its AC flow breaks is reported. The hour as linearised for
    the plan kept, its clearing, the AC flow of its plan (None where it has none) and how many linearised clearings
    were made."""
    solve, base = hour.feeder.ac.solve, hour
    done = _plate(hour) or _on_feeder(hour, priced=False)  # the copper plate's plan, with the limits it breaks
    point = solve(*hour.loads(done.step_mw, done.shed))
    if point is None:  # the copper plate's plan has no AC solution: LinDistFlow's, which keeps its limits, may
        done = _on_feeder(hour)
        point = solve(*hour.loads(done.step_mw, done.shed))
        if point is None:
            return hour, done, None, 0
    # The clearings linearise at their LPs' own plans until one is its own operating point; only then are its prices
    # worked out and its awards decided from them, and where that moves the plan, every clearing from there on is.
    priced = False
    # each linearised clearing, how far its plan's AC flow breaks the limits, and that flow
    tried: list[tuple[float, _Hour, _Cleared | _Plan, OperatingPoint]] = []
    for iteration in range(1, MAX_AC_ITERATIONS + 1):
        linearised = dataclasses.replace(hour, at=hour.feeder.linearised(point, done.rows))
        try:
            cleared = _on_feeder(linearised, done.rows, priced)
        except ValueError:  # no plan meets the limits linearised there: the last one that did, or LinDistFlow's
            return _answered(hour, done, point, iteration - 1) if hour.at is not None else _lindistflow(hour)
        flow = _flow_of(linearised, cleared, point)
        if flow is None:  # a plan the AC flow cannot carry: the last linearised one that it could, or LinDistFlow's
            return _answered(hour, done, point, iteration - 1) if hour.at is not None else _lindistflow(hour)
        hour, done, point, broken, moved = linearised, cleared, flow, _broken(linearised, flow), _moved(flow, linearised)
        if broken <= 1.0 and moved <= AC_PLAN_TOLERANCE:
            if isinstance(done, _Cleared):
                break
            done = _awarded(hour, done.solution)
            point = _flow_of(hour, done, point)
            if point is None:  # the shares moved the plan where the AC flow has no solution: reported so
                return hour, done, None, iteration
            if _broken(hour, point) <= 1.0 and _moved(point, hour) <= AC_PLAN_TOLERANCE:
                break
            priced = True
        tried.append((broken, hour, done, point))
        if len(tried) >= 3 and np.abs(tried[-3][2].step_mw - done.step_mw).max(initial=0.0) <= AC_CYCLE_TOLERANCE:
            settled = _settle(base, tried[-2][2], done, point)
            if settled is not None:
                hour, done, point, more = settled
                return hour, done, point, iteration + more
            _, hour, done, point = min(tried[-2:], key=lambda t: t[0])
            break
    return _answered(hour, done, point, iteration)


def _settle(hour: _Hour, one: _Cleared | _Plan, other: _Cleared | _Plan,
            near: OperatingPoint) -> tuple[_Hour, _Cleared, OperatingPoint, int] | None:
    """Settle an hour whose linearised clearings alternate between the plans ``one`` and ``other`` (docs/market.md,
    "Plans that alternate"): a step whose own losses move its bus's price across its bid (or steps that trade one
    binding limit for another) is in at one operating point and out at the other, and the plan that is its own
    operating point lies between them, those steps part-accepted where their bus prices meet their bids.

    From the plans' midpoint, each clearing is the LP linearised at the last plan with a proximal term over the
    steps that alternate: the losses' curvature there, (x - x_k)' H (x - x_k) / 2 times the energy price, H the
    second derivative of the AC losses in those steps' MW (2 r (1 + tan(phi)^2) / U per line they share), raised
    fourfold whenever a move is not half the one before; a sequential quadratic programme with a proximal
    (Levenberg-Marquardt) term (Nocedal and Wright 2006, ch. 18; Rockafellar 1976). Once a plan lies within
    AC_PLAN_TOLERANCE of the point it was linearised at, the term is nil to first order there: the alternating
    steps are held at that plan's MW, shared equally by steps alike (``_alike``), and the hour is the LP linearised
    there with them held (``_Hour.pinned``): its prices and the other awards are that LP's, by the rule of
    ``_awarded``. The hour, its clearing, the AC flow of its plan and the clearings made; None where the
    iterations end without such a plan within MAX_AC_ITERATIONS."""
    feeder = hour.feeder
    steps = np.flatnonzero(np.abs(one.step_mw - other.step_mw) > AC_CYCLE_TOLERANCE)
    rows = np.union1d(one.rows, other.rows)
    plan = (one.step_mw + other.step_mw) / 2
    point = feeder.ac.solve(*hour.loads(plan, (one.shed + other.shed) / 2), near)
    base = max(abs(one.energy), 1.0)
    weight, step = base, np.zeros(len(steps))
    for iteration in range(1, MAX_AC_ITERATIONS + 1):
        if point is None:
            return None
        linearised = dataclasses.replace(hour, at=feeder.linearised(point, rows))
        term = Proximal(steps, weight * _curvature(linearised, steps), plan[steps])
        try:
            sol = linearised.solve(rows, term)
        except ValueError:
            return None
        if sol.flow is None:
            return None
        moved, rows = _moved(sol.flow, linearised), sol.rows
        last, step, plan = step, sol.step_mw[steps] - plan[steps], sol.step_mw
        if moved <= AC_PLAN_TOLERANCE:
            _, a_eq, _, a_ub, _, _, _ = sol.lp
            pinned = np.full(len(plan), np.nan)
            pinned[steps] = _equal_shares(plan[steps], _alike(np.vstack([a_eq, a_ub]), steps, hour.book),
                                          hour.book.quantity[steps])
            settled = dataclasses.replace(linearised, pinned=pinned)
            done = _on_feeder(settled, rows)
            flow = _flow_of(settled, done, sol.flow)
            if flow is not None and _moved(flow, settled) <= AC_PLAN_TOLERANCE and _supported(settled, done):
                return settled, done, flow, iteration + 1
        # a move back against the last one overshot: more weight; one further on: less, down to the losses' own
        weight = weight * 4.0 if step @ last < 0 else max(weight / 2.0, base)
        point = sol.flow
    return None


def _supported(hour: _Hour, done: _Cleared) -> bool:
    """Whether the prices of ``done`` (its LP's duals, before ``_snap``) support the awards of the steps the hour
    holds (``_Hour.pinned``) within AC_PRICE_TOLERANCE: each part-accepted one at its bid, each accepted in full in
    the money or at its price, each rejected out of it or at its price."""
    held = np.flatnonzero(np.isfinite(hour.pinned))
    book = hour.book
    price = (done.energy + done.loss + done.congestion + done.voltage)[hour.bus[held]]
    surplus = np.where(book.quantity[held] > 0, book.price[held] - price, price - book.price[held])
    share = hour.pinned[held] / book.quantity[held]
    off = np.where(share >= 1.0 - LIMIT_TOLERANCE, -surplus, np.where(share <= LIMIT_TOLERANCE, surplus,
                                                                          np.abs(surplus)))
    return bool((off <= AC_PRICE_TOLERANCE).all())


def _curvature(hour: _Hour, steps: np.ndarray) -> np.ndarray:
    """The second derivative of the AC losses in the MW of ``steps`` (each with tan(phi) Mvar) at the hour's
    operating point, steps x steps: sum over lines of 2 r (1 + tan(phi)^2) / U at the line's sending end, for each
    pair of steps both below the line (MW per MW^2)."""
    feeder, network = hour.feeder, hour.feeder.network
    below = network.downstream[:, hour.bus[steps]].astype(float)
    weight = 2.0 * feeder.ac.r * (1.0 + feeder.tan_phi ** 2) / hour.at.point.u[network.parent]
    return exact.weighted(below.T, weight[:, None] * below, axis=0)


def _flow_of(hour: _Hour, cleared: _Cleared | _Plan, near: OperatingPoint) -> OperatingPoint | None:
    """The AC flow of the clearing's plan, solved from ``near`` (None where it has none). Constraint generation solved
    it for the LP's plan: the awards' loads are the LP's but for rounding in a pro-rata share, and where they are
    the same bits, so is their AC flow."""
    loads = hour.loads(cleared.step_mw, cleared.shed)
    known = cleared.flow
    return known if known is not None and known.of(*loads) else hour.feeder.ac.solve(*loads, near)


def _broken(hour: _Hour, point: OperatingPoint) -> float:
    """How far the AC flow ``point`` breaks the feeder's limits, in tolerances: at most 1 where it keeps them."""
    return max(_voltage_excess(hour.feeder.network, point.v) / AC_VOLTAGE_TOLERANCE,
               _overload(hour.feeder, point) / AC_LOADING_TOLERANCE)


def _moved(point: OperatingPoint, hour: _Hour) -> float:
    """How far the loads of the AC flow ``point`` lie from the operating point ``hour`` is linearised at (MW, Mvar)."""
    at = hour.at.point
    return float(max(np.abs(point.p - at.p).max(), np.abs(point.q - at.q).max()))


def _answered(hour: _Hour, done: _Cleared | _Plan, point: OperatingPoint | None,
            iterations: int) -> tuple[_Hour, _Cleared, OperatingPoint | None, int]:
    """``_ac_faithful``'s answer: ``done`` priced and awarded (``_awarded``), and the AC flow of that plan."""
    if isinstance(done, _Cleared):
        return hour, done, point, iterations
    shared = _awarded(hour, done.solution)
    return hour, shared, None if point is None else _flow_of(hour, shared, point), iterations


def _lindistflow(hour: _Hour) -> tuple[_Hour, _Cleared, OperatingPoint | None, int]:
    """The hour's LinDistFlow clearing as ``_ac_faithful`` answers it: the hour, its clearing, the AC flow of its plan
    (None where it has none) and no linearised clearing."""
    done = _on_feeder(hour)
    return hour, done, hour.feeder.ac.solve(*hour.loads(done.step_mw, done.shed)), 0


# --- the day ------------------------------------------------------------------------------------------------------

def agent_buses(network: Network, buses: Mapping[str, object], names: Sequence[str]) -> np.ndarray:
    """The bus index of each agent of ``names``, from ``buses`` (agent -> bus name or index); ValueError (a
    ``NetworkError`` for a bus) with a one-line reason."""
    if not isinstance(buses, Mapping):
        raise ValueError("buses must map each agent id to its bus")
    missing = [a for a in names if a not in buses]
    if missing:
        raise ValueError(f"agent {missing[0]} has no bus on network {network.name}")
    return np.array([network.bus_of(buses[a], f"bus of agent {a}") for a in names], dtype=int)


def _hours(bids, network, buses, iso_price, import_limit, export_limit, agents, voll, margin, curve, method,
           spill_price):
    if method not in CLEARING_METHODS:
        raise ValueError(f"method must be one of {', '.join(CLEARING_METHODS)}, got {method!r}")
    if not isinstance(network, Network):
        raise ValueError(f"network must be a scenarios.network.Network, got {type(network).__name__}")
    if not isinstance(curve, IsoCurve):
        raise ValueError(f"curve must be a clearing.IsoCurve, got {type(curve).__name__}")
    bids, names, iso, imp, exp = market_inputs(bids, iso_price, import_limit, export_limit, agents)
    voll = finite(voll, "voll")
    if voll <= 0:
        raise ValueError(f"voll must be > 0, got {voll}")
    spill_price = finite(spill_price, "spill_price")
    if not 0 <= spill_price <= voll:
        raise ValueError(f"spill_price must be between 0 and voll ({voll:g}), got {spill_price:g}")
    feeder = Feeder(network, margin)  # a margin that leaves a bus no band is refused here
    at = agent_buses(network, buses, names)

    def hour(h: int) -> _Hour:
        book = hour_book(bids, names, h)
        order = np.lexsort((book.owner, book.quantity, book.price, at[book.owner]))
        canonical = Book(book.owner[order], book.price[order], book.quantity[order])
        return _Hour(feeder, canonical, at[canonical.owner], network.fixed_p[h], network.fixed_q[h],
                     segments(curve, iso[h], imp[h], exp[h]), voll, spill_price)

    return names, at, feeder, hour


def hour_program(bids: Iterable[BidCurve], network: Network, buses: Mapping[str, object], hour: int,
                 iso_price: float | Sequence[float], import_limit: float | Sequence[float],
                 export_limit: float | Sequence[float], agents: Iterable[str] = (), voll: float = VOLL,
                 margin: float = 0.0, curve: IsoCurve = FLAT, method: str = "lindistflow",
                 spill_price: float = 0.0) -> HourProgram:
    """The LP of hour index ``hour`` as ``clear_network`` solves it when the copper plate does not hold (here always
    solved, whether or not it does), written out whole: every line facet and voltage limit, those left out of the
    solve with a zero dual; with ``method`` "ac", the LP of the last corrected clearing. For checking the prices
    (KKT conditions, sensitivities)."""
    if isinstance(hour, bool) or not isinstance(hour, int) or not 0 <= hour < HOURS:
        raise ValueError(f"hour must be an hour index 0..{HOURS - 1}, got {hour!r}")
    names, at, feeder, make = _hours(bids, network, buses, iso_price, import_limit, export_limit, agents, voll,
                                     margin, curve, method, spill_price)
    h = make(hour)
    if method == "ac":
        h = _ac_faithful(h)[0]
    sol = h.solve(_copper_plate(h)[1])
    every, shed_every = feeder.rows, h.shed_buses
    g_p, g_q, b = h.limits(every)
    c, a_eq, b_eq, a_ub, b_ub, lower, upper = h.program(g_p, g_q, b, shed_every)
    s, k = len(h.book.quantity), len(shed_every)
    solved = np.concatenate([np.arange(s), s + np.searchsorted(shed_every, sol.shed_at), s + k + np.arange(sol.segments)])
    x = np.zeros(len(c))
    x[solved] = sol.res.x
    ub_dual = np.zeros(len(every))
    ub_dual[np.searchsorted(every, sol.rows)] = sol.ub_dual
    lower_dual, upper_dual = np.zeros(len(c)), np.zeros(len(c))
    lower_dual[solved], upper_dual[solved] = sol.res.lower.marginals, sol.res.upper.marginals
    # curtailments left at 0: their reduced cost, VOLL - value for a load, spill price + value for a generation, >= 0
    left_out = np.setdiff1d(np.arange(s, s + k), solved)
    buses_out = shed_every[left_out - s]
    lower_dual[left_out] = h.shed_cost(buses_out) + h.shed_sign[buses_out] * h.shed_value(sol, buses_out)
    buses_all = np.arange(network.n_buses)
    return HourProgram(c, a_eq, b_eq, a_ub, b_ub, lower, upper, feeder.row_names(every), shed_every, x,
                       sol.res.eqlin.marginals, ub_dual, lower_dual, upper_dual, float(sol.res.fun),
                       -h.gain(feeder.tan_phi, buses_all), g_p + feeder.tan_phi * g_q)


def clear_network(bids: Iterable[BidCurve], network: Network, buses: Mapping[str, object],
                  iso_price: float | Sequence[float], import_limit: float | Sequence[float],
                  export_limit: float | Sequence[float], agents: Iterable[str] = (),
                  voll: float = VOLL, margin: float = 0.0, curve: IsoCurve = FLAT,
                  method: str = "lindistflow", spill_price: float = 0.0) -> NetworkClearing:
    """Clear one market day on ``network``: per hour the bus prices, the awards and the feeder's state.

    ``buses`` maps every bidder and every name in ``agents`` to its bus (a name or index of ``network.buses``, not
    the substation). ``iso_price`` ($/MWh) and the substation's ``import_limit`` and ``export_limit`` (MW, on its
    exchange with the ISO, fixed load included) are a scalar or 24 hourly values, as in ``clearing.clear``.
    ``voll``: the value of lost load, $/MWh. ``margin`` (p.u., >= 0): LinDistFlow's voltages are held within
    v_min + margin and v_max - margin, room for its error against AC (docs/network.md, "The AC check"). ``curve``:
    the ISO's blocks around its price, which price the substation's exchange (``clearing.IsoCurve``). ``method``:
    "lindistflow" clears on LinDistFlow alone; "ac" on LinDistFlow corrected at the AC flow of its own plan, until
    the plan is its own operating point (docs/market.md, "AC-faithful clearing"). ``spill_price`` ($/MWh, 0 to
    ``voll``): what spilling a MW of the feeder's fixed generation (a bus's negative fixed load) costs the welfare,
    as ``voll`` prices shedding load. Raises ValueError (a ``NetworkError`` for a bus) with a one-line reason.
    """
    names, at, feeder, make = _hours(bids, network, buses, iso_price, import_limit, export_limit, agents, voll,
                                     margin, curve, method, spill_price)
    out, points, columns, iterations = [], [], [], []
    for h in range(HOURS):  # each hour's clearing and the AC flow of its plan (None where it has none)
        hour, done, point, k = (_ac_faithful if method == "ac" else _lindistflow)(make(h))
        out.append((hour, done))
        points.append(point)
        iterations.append(k)
        columns.append(per_agent(hour.book, done.step_mw, len(names)))
    flows_p, flows_q, loading, volts, exchange, welfare, excess, overload = [], [], [], [], [], [], [], []
    for (hour, done), point in zip(out, points):
        p, q = hour.loads(done.step_mw, done.shed)
        excess.append(math.nan if point is None else _voltage_excess(network, point.v))
        overload.append(math.nan if point is None else _overload(feeder, point))
        if method == "ac" and point is not None:
            fp, fq, u = point.flow_p, point.flow_q, point.u
            p0 = math.fsum(np.append(p, point.losses))
            left = feeder.ac_left_sides(point)[0]
        else:
            fp, fq, u = feeder.state(p, q)
            p0 = math.fsum(np.concatenate([hour.fixed_p, done.step_mw, hour.shed_sign * done.shed]))
            left = feeder.left_sides(p, q)
        flows_p.append(fp)
        flows_q.append(fq)
        loading.append(feeder.loading(left))
        volts.append(np.sqrt(np.maximum(u, 0.0)))
        exchange.append(p0 + 0.0)
        welfare.append(math.fsum(np.concatenate([hour.book.price * done.step_mw, [-hour.curve.cost(p0)],
                                                 -hour.shed_cost(np.arange(len(done.shed))) * done.shed])) + 0.0)
    bus_price = np.array([done.bus_price for _, done in out])
    awards = {a: tuple(columns[h][i] for h in range(HOURS)) for i, a in enumerate(names)}
    agent_price = {a: tuple(float(bus_price[h, at[i]]) for h in range(HOURS)) for i, a in enumerate(names)}
    energy = np.array([done.energy for _, done in out])
    facet, line_shadow, side, voltage_shadow = zip(*(feeder.binding(done.held, done.relief) for _, done in out))

    def frozen(rows, dtype=float) -> np.ndarray:
        a = np.array(rows, dtype=dtype)
        a.setflags(write=False)
        return a

    return NetworkClearing(
        price=tuple(float(e) for e in energy), awards=awards, congested=tuple(done.congested for _, done in out),
        agent_price=agent_price, bus_price=frozen(bus_price), energy=frozen(energy),
        congestion=frozen([done.congestion for _, done in out]), voltage=frozen([done.voltage for _, done in out]),
        binding_facet=frozen(facet, int), line_shadow_price=frozen(line_shadow), binding_voltage=frozen(side, int),
        voltage_shadow_price=frozen(voltage_shadow), flow_p=frozen(flows_p), flow_q=frozen(flows_q),
        limit_loading=frozen(loading), voltage_pu=frozen(volts),
        shed_mw=frozen([np.where(hour.fixed_p > 0, done.shed, 0.0) for hour, done in out]),
        spill_mw=frozen([np.where(hour.fixed_p < 0, done.shed, 0.0) for hour, done in out]),
        exchange_mw=tuple(exchange), welfare=tuple(welfare),
        method=method, loss=frozen([done.loss for _, done in out]), iterations=tuple(iterations),
        ac_voltage_excess_pu=tuple(excess), ac_overload=tuple(overload))


def _voltage_excess(network: Network, v: np.ndarray) -> float:
    """How far the most distant bus voltage lies outside its limits (p.u.; 0 if none does)."""
    return float(max(0.0, np.max(network.v_min - v), np.max(v - network.v_max)))


def _overload(feeder: Feeder, point: OperatingPoint) -> float:
    """The largest share of a line's rating by which its apparent power at its sending end (the larger) exceeds it,
    0 if none does."""
    lost_p, lost_q = feeder.ac.r * point.current2, feeder.ac.x * point.current2
    sending = np.maximum(np.hypot(point.flow_p, point.flow_q), np.hypot(point.flow_p - lost_p, point.flow_q - lost_q))
    return float(max(0.0, np.max(sending / feeder.s_max - 1.0)))
