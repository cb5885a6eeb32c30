"""Operating envelopes on a feeder: per hour and bus, how far each microgrid may move its metered transfer above its
award (its import room) and below it (its export room) without breaking the feeder whatever the others do within
theirs (docs/network.md, "Operating envelopes").

Pure: a day's ``NetworkClearing``, its ``Network``, the agents' buses, the voltage margin and the substation's limits
in, two (24 x buses) arrays of rooms >= 0 (MW) out. Under LinDistFlow every limit is linear in the buses' loads,
G_P p + G_Q q <= b (``distflow.Feeder``): line facets, voltage limits narrowed by the margin, and the substation's
import and export limits. At the hour's planned state (the fixed loads at their hourly values, every microgrid at its
award) limit i has slack s_i (of the AC flow there, for a day cleared on it); a microgrid at bus j moving by d MW (and
tan(phi) d Mvar) changes its left side by g_ij d, g = G_P + tan(phi) G_Q.

On a radial feeder each limit's g has one sign across the buses (a line facet's is n_P + tan(phi) n_Q times 0 or 1,
a voltage limit's sensitivities R + tan(phi) X are all >= 0 for its lower limit and <= 0 for its upper one). So a
limit with g >= 0 is moved towards its bound only by microgrids importing more than their awards, and one with
g <= 0 only by microgrids importing less: with import rooms u_j and export rooms e_j, every limit holds with every
microgrid at the worst end of its range if and only if

    sum over microgrids a of g_{i, bus(a)} u_{bus(a)} <= max(s_i, 0)     for every limit i with g >= 0
    sum over microgrids a of -g_{i, bus(a)} e_{bus(a)} <= max(s_i, 0)    for every limit i with g <= 0

two problems that share no limit. Each is shared max-min fairly by progressive filling: every bus with a microgrid
and not yet frozen gains room at the same pace; when a limit's slack runs out, the buses with a nonzero g in it
freeze at their room; repeat until every such bus is frozen. A limit broken as planned has no slack: the buses that
move it towards its bound get no room that way, and keep the room the other way.

For loads x >= 0 the rate at which the rooms use limit i is (G_P x + G_Q tan(phi) x)_i, taken where it is positive
for the import rooms and where it is negative for the export rooms: one evaluation of ``Feeder.left_sides`` per round
of the filling, and ``Feeder.behind`` says which buses a binding limit freezes. Nothing is as large as limits x
buses.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from scenarios.horizon import HOURS, hourly
from scenarios.network import Network

from .distflow import Feeder, NetworkClearing, agent_buses

# A limit whose slack runs out within this share of the round's rise binds with the first (floating-point ties).
TIE = 1e-12


@dataclass(frozen=True, eq=False)  # arrays inside
class Rooms:
    """A day's operating envelope, per hour and bus (24 x buses each, ``network.buses`` order, read-only, MW >= 0):
    each microgrid at bus j may meter anywhere in [award - ``export_mw``, award + ``import_mw``]. 0 at buses with no
    microgrid."""

    import_mw: np.ndarray
    export_mw: np.ndarray


def operating_envelope(clearing: NetworkClearing, network: Network, buses: Mapping[str, str],
                       import_limit: float | Sequence[float], export_limit: float | Sequence[float],
                       margin: float = 0.0) -> Rooms:
    """The rooms each microgrid has per hour above and below its award (``Rooms``): within them no line, voltage
    (within ``margin`` p.u. of its limits) or substation limit (``import_limit``, ``export_limit``: MW, scalar or 24)
    breaks under LinDistFlow from the planned state, whose slacks are the AC flow's for a day cleared on it
    (``clearing.method`` "ac"). ``buses`` maps every agent of ``clearing.awards`` to its bus. ValueError, one line,
    on bad input."""
    names = sorted(clearing.awards)
    at = agent_buses(network, buses, names)
    imp = hourly(import_limit, "import_limit", non_negative=True)
    exp = hourly(export_limit, "export_limit", non_negative=True)
    feeder = Feeder(network, margin)
    n = network.n_buses
    count = np.bincount(at, minlength=n).astype(float)  # microgrids per bus: each takes the bus's room
    injection = np.zeros((n, HOURS))
    np.add.at(injection, at, np.array([clearing.awards[a] for a in names], float).reshape(len(names), HOURS))
    p = network.fixed_p + injection.T
    q = network.fixed_q + feeder.tan_phi * injection.T
    rooms = np.zeros((2, HOURS, n))
    for h in range(HOURS):
        slack = _slack(feeder, p[h], q[h], imp[h], exp[h], clearing.method == "ac")
        rooms[:, h] = [_fill(feeder, count, slack, sign) for sign in (1.0, -1.0)]
    rooms.setflags(write=False)
    return Rooms(rooms[0], rooms[1])


def _slack(feeder: Feeder, p: np.ndarray, q: np.ndarray, import_limit: float, export_limit: float,
           ac: bool) -> np.ndarray:
    """Every limit's slack at the planned loads p, q (per bus), clamped at 0: the feeder's (``feeder.rows``), then
    the substation's import and export; of the AC flow with ``ac`` (all 0 where it has no solution), else of
    LinDistFlow (lossless: the import is the sum of the loads)."""
    if not ac:
        left, p0 = feeder.left_sides(p, q), float(np.sum(p))
    else:
        point = feeder.ac.solve(p, q)
        if point is None:
            return np.zeros(len(feeder.rows) + 2)
        left, p0 = feeder.ac_left_sides(point)[0], float(np.sum(p)) + point.losses
    return np.maximum(np.concatenate([feeder.bounds - left, [import_limit - p0, p0 + export_limit]]), 0.0)


def _fill(feeder: Feeder, count: np.ndarray, slack: np.ndarray, sign: float) -> np.ndarray:
    """One hour's rooms one way by progressive filling (``sign`` +1: import rooms, -1: export rooms), from every
    limit's ``slack`` (``_slack``). A room one way uses the limits whose left side rises with it: the feeder's with a
    g of that sign, and the substation's import (import rooms) or export (export rooms), whose g is 1 at every bus."""
    room = np.zeros(len(count))
    free = count > 0
    while free.any():
        x = np.where(free, count, 0.0)  # what one MW more of room for every free bus costs each limit
        total = x.sum()
        rate = np.concatenate([sign * feeder.left_sides(x, feeder.tan_phi * x), [sign * total, -sign * total]])
        rising = np.flatnonzero(rate > 0)
        ratio = slack[rising] / rate[rising]
        rise = float(ratio.min())
        room[free] += rise
        slack = np.maximum(slack - rise * np.maximum(rate, 0.0), 0.0)
        binding = rising[ratio <= rise * (1 + TIE)]
        if (binding >= len(feeder.rows)).any():  # the substation's: every microgrid moves it
            break
        frozen = free & feeder.behind(feeder.rows[binding])
        if not frozen.any():  # a limit that rose but that no free bus moves: only rounding can do it; never loop
            break
        free &= ~frozen
    return room
