"""Operating envelopes on a feeder: per hour and bus, how far each microgrid may move its metered transfer from its
award, either way, without breaking the feeder whatever the others do within theirs (docs/network.md, "Operating
envelopes").

Pure: a day's ``NetworkClearing``, its ``Network``, the agents' buses, the voltage margin and the substation's limits
in, a (24 x buses) array of rooms r_j >= 0 (MW) out. Under LinDistFlow every limit is linear in the buses' loads,
G_P p + G_Q q <= b (``distflow.Feeder``): line facets, voltage limits narrowed by the margin, and the substation's
import and export limits. At the hour's planned state (the fixed loads at their hourly values, every microgrid at its
award) limit i has slack s_i; a microgrid at bus j moving by d MW (and tan(phi) d Mvar) changes its left side by
g_ij d, g = G_P + tan(phi) G_Q. The rooms hold every limit even with every microgrid at the worst end of its range:

    sum over microgrids a of |g_{i, bus(a)}| r_{bus(a)} <= max(s_i, 0)    for every limit i

and are shared max-min fairly by progressive filling: every bus with a microgrid and not yet frozen gains room at the
same pace; when a limit's slack runs out, the buses with a nonzero g in it freeze at their room; repeat until every
such bus is frozen. A limit broken as planned has no slack: the buses behind it get no room.

On a radial feeder each limit's g has one sign across the buses (a line facet's is n_P + tan(phi) n_Q times 0 or 1,
a voltage limit's sensitivities R + tan(phi) X are all >= 0), so for loads x >= 0 the robust left side
sum_j |g_ij| x_j is |G_P x + G_Q tan(phi) x|: one evaluation of ``Feeder.left_sides`` per round of the filling, and
``Feeder.behind`` says which buses a binding limit freezes. Nothing is as large as limits x buses.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from scenarios.horizon import HOURS, hourly
from scenarios.network import Network

from .distflow import Feeder, NetworkClearing, agent_buses

# A limit whose slack runs out within this share of the round's rise binds with the first (floating-point ties).
TIE = 1e-12


def operating_envelope(clearing: NetworkClearing, network: Network, buses: Mapping[str, str],
                       import_limit: float | Sequence[float], export_limit: float | Sequence[float],
                       margin: float = 0.0) -> np.ndarray:
    """(24 x buses, ``network.buses`` order, read-only) the room r_j (MW) of each microgrid at bus j per hour: each
    may meter anywhere in [award - r_j, award + r_j] and no line, voltage (within ``margin`` p.u. of its limits) or
    substation limit (``import_limit``, ``export_limit``: MW, scalar or 24) breaks under LinDistFlow. 0 at buses with
    no microgrid. ``buses`` maps every agent of ``clearing.awards`` to its bus. ValueError, one line, on bad input."""
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
    room = np.array([_fill(feeder, count, p[h], q[h], imp[h], exp[h]) for h in range(HOURS)])
    room.setflags(write=False)
    return room


def _fill(feeder: Feeder, count: np.ndarray, p: np.ndarray, q: np.ndarray, import_limit: float,
          export_limit: float) -> np.ndarray:
    """One hour's rooms by progressive filling, from the planned loads p, q (per bus). The limits are the feeder's
    (``feeder.rows``) and then the substation's import and export, whose g is 1 at every bus (LinDistFlow is
    lossless: the import is the sum of the loads)."""
    p0 = float(np.sum(p))
    slack = np.maximum(np.concatenate([feeder.bounds - feeder.left_sides(p, q),
                                       [import_limit - p0, p0 + export_limit]]), 0.0)
    room = np.zeros(len(count))
    free = count > 0
    while free.any():
        x = np.where(free, count, 0.0)  # what one MW more of room for every free bus costs each limit
        rate = np.concatenate([np.abs(feeder.left_sides(x, feeder.tan_phi * x)), np.full(2, x.sum())])
        rising = np.flatnonzero(rate > 0)
        ratio = slack[rising] / rate[rising]
        rise = float(ratio.min())
        room[free] += rise
        slack = np.maximum(slack - rise * rate, 0.0)
        binding = rising[ratio <= rise * (1 + TIE)]
        if (binding >= len(feeder.rows)).any():  # the substation's: every microgrid moves it
            break
        frozen = free & feeder.behind(feeder.rows[binding])
        if not frozen.any():  # a limit that rose but that no free bus moves: only rounding can do it; never loop
            break
        free &= ~frozen
    return room
