"""The AC power-flow check of a feeder's hours: pandapower's Newton-Raphson on each hour's loads, beside LinDistFlow.

The DMO clears on LinDistFlow (Baran and Wu 1989), which neglects losses and so overestimates voltages; this runs
the full AC power flow of the same hours and reports, hour by hour, the lowest and highest voltage, the most
loaded line, every limit the AC flow breaks and how far LinDistFlow's voltages and flows are from AC's
(docs/network.md, "The AC check"). Pure: a network and loads in, frozen ``HourCheck``s out. pandapower is imported
inside ``check_hours`` only (it loads matplotlib) and kept quiet.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, fields

import numpy as np

from scenarios.horizon import HOURS
from scenarios.network import Network, quiet_pandapower

NOT_CONVERGED = "no AC solution"  # the one violation of an hour whose Newton-Raphson does not converge
# A limit is broken when the AC flow passes it by more than this (p.u. of voltage, share of a rating): a clearing
# that holds a limit exactly (the AC-faithful one, to its LP's tolerances) meets it to about 1e-7
VIOLATION_TOLERANCE = 1e-6
# pandapower reuses the admittance matrix between hours and updates only the loads (runpp's ``recycle``)
_RECYCLE = {"bus_pq": True, "trafo": False, "gen": False}
_ARRAYS = ("v_pu", "loading")  # per-bus and per-line fields, left out of as_dict (profile gives them)


@dataclass(frozen=True)
class HourCheck:
    """The AC check of one hour (docs/network.md, "The AC check"). ``hour``: its index in the day (0..23).
    ``converged``: whether Newton-Raphson found the AC solution; if not, every number is NaN, every name empty
    and ``violations`` is (``NOT_CONVERGED``,).

    ``v_min_pu``/``v_min_bus``, ``v_max_pu``/``v_max_bus``: the lowest and highest AC voltage and their bus;
    ``max_loading``/``max_loading_line``: the highest loading (apparent power at the line's sending end over its
    ``s_max_mva``, a fraction) and its line ("from-to"); ``voltage_error_pu``: max over buses of
    |V LinDistFlow - V AC|; ``flow_error_mw``: max over lines of |P LinDistFlow - P AC| at the line's substation
    end; ``losses_mw``: AC losses; ``substation_mw``: AC import at the substation; ``violations``: one short string
    per limit the AC flow breaks; ``margin``: the voltage margin (p.u.) the clearing held, as the caller said.
    ``v_pu`` (per bus, the network's order) and ``loading`` (per line) are the hour's profiles (``profile()``).
    """

    hour: int
    converged: bool
    v_min_pu: float
    v_min_bus: str
    v_max_pu: float
    v_max_bus: str
    max_loading: float
    max_loading_line: str
    voltage_error_pu: float
    flow_error_mw: float
    losses_mw: float
    substation_mw: float
    violations: tuple[str, ...]
    margin: float
    v_pu: tuple[float, ...] = field(repr=False)
    loading: tuple[float, ...] = field(repr=False)

    def as_dict(self) -> dict:
        """The hour's figures as JSON-ready values, without the per-bus and per-line profiles: voltages, MW and
        the margin to 1e-6 (p.u., MW), loadings to 1e-4 (0.01 %), and None where the hour has no AC solution."""
        out = {}
        for f in fields(self):
            if f.name in _ARRAYS:
                continue
            value = getattr(self, f.name)
            if isinstance(value, float):
                value = _rounded(value, 4 if f.name == "max_loading" else 6)
            out[f.name] = list(value) if isinstance(value, tuple) else value
        return out

    def profile(self) -> dict:
        """The hour's AC voltage per bus (``v_pu``, the network's bus order) and loading per line (``loading``,
        its line order), JSON-ready as in ``as_dict``: the voltage along the feeder, for a figure."""
        return {"hour": self.hour, "v_pu": [_rounded(v, 6) for v in self.v_pu],
                "loading": [_rounded(x, 4) for x in self.loading]}


def _rounded(x: float, digits: int) -> float | None:
    return round(x, digits) + 0.0 if math.isfinite(x) else None


def check_hours(network: Network, p_mw, *, q_mvar=None, hours: Sequence[int] | None = None,
                margin: float = 0.0) -> tuple[HourCheck, ...]:
    """The AC check of H hours of a feeder: one ``HourCheck`` per row of ``p_mw``.

    ``p_mw`` (H x buses): the microgrids' net import per bus (MW, + import), added to the network's fixed load of
    the same hour; its substation column must be 0. ``q_mvar`` (H x buses) their reactive power, by default
    ``network.tan_phi`` x ``p_mw``. ``hours``: which hours of the day (0..23) the rows are, so the fixed loads line
    up; by default rows 0..H-1 (H <= 24). ``margin`` (p.u., >= 0): the voltage margin the clearing held
    (LinDistFlow's voltages kept within v_min + margin .. v_max - margin); it is reported beside the check and
    changes nothing in it: violations are always against the network's own limits.

    One pandapower net is built per call; hour after hour only its loads change and Newton-Raphson starts from
    the previous hour's solution (from a flat start for the first hour and after an hour with no solution). An
    hour that does not converge is reported with ``converged`` False, never raised. ValueError on bad input.
    """
    p, q, rows = _inputs(network, p_mw, q_mvar, hours)
    margin = _margin(margin)
    load_p = network.fixed_p[rows] + p
    load_q = network.fixed_q[rows] + q
    ldf_p, _, ldf_v = network.lindistflow(load_p, load_q)
    with quiet_pandapower():
        import pandapower as pp  # ~1 s and matplotlib: only when a check is asked for

        net = _pandapower_net(pp, network)
        checks, warm = [], False
        for k, hour in enumerate(rows):
            net.load["p_mw"] = load_p[k]
            net.load["q_mvar"] = load_q[k]
            warm = _solve(pp, net, warm)
            ac = _ac_results(net) if warm else None
            checks.append(_hour_check(network, int(hour), ac, ldf_p[k], ldf_v[k], margin))
    return tuple(checks)


def _inputs(network: Network, p_mw, q_mvar, hours) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = _table(p_mw, "p_mw", network, None)
    q = network.tan_phi * p if q_mvar is None else _table(q_mvar, "q_mvar", network, len(p))
    if hours is None:
        if len(p) > HOURS:
            raise ValueError(f"p_mw has {len(p)} rows; give ``hours`` to say which hours of the day they are")
        return p, q, np.arange(len(p))
    rows = np.asarray(hours)
    if rows.shape != (len(p),) or rows.dtype.kind not in "iu" or rows.min() < 0 or rows.max() >= HOURS:
        raise ValueError(f"hours must give one hour index 0..{HOURS - 1} per row of p_mw ({len(p)}), "
                         f"got {hours!r}")
    return p, q, rows


def _table(values, what: str, network: Network, rows: int | None) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if a.ndim != 2 or a.shape[1] != network.n_buses or len(a) == 0 or (rows is not None and len(a) != rows):
        want = f"{rows if rows is not None else 'H >= 1'} x {network.n_buses}"
        raise ValueError(f"{what} must be hours x buses ({want}) for network {network.name}, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{what} must be finite")
    if np.any(a[:, network.root]):
        raise ValueError(f"{what}: the substation bus {network.substation} carries no microgrid; its column must be 0")
    return a


def _margin(margin) -> float:
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not 0 <= margin < 0.5:
        raise ValueError(f"margin must be a voltage margin in p.u., 0 <= margin < 0.5, got {margin!r}")
    return float(margin)


def _pandapower_net(pp, network: Network):
    """The feeder as a pandapower net: bus i and line l are the network's, each line 1 km of its r and x ohm
    with no shunt capacitance, one load per bus, the substation held at ``v_substation`` by the external grid."""
    net = pp.create_empty_network(name=network.name, sn_mva=1.0)
    pp.create_buses(net, network.n_buses, vn_kv=network.base_kv, name=list(network.buses))
    pp.create_ext_grid(net, network.root, vm_pu=network.v_substation)
    pp.create_lines_from_parameters(net, network.parent, network.child, length_km=1.0, r_ohm_per_km=network.r_ohm,
                                    x_ohm_per_km=network.x_ohm, c_nf_per_km=0.0,
                                    max_i_ka=network.s_max_mva / (math.sqrt(3) * network.base_kv))
    pp.create_loads(net, np.arange(network.n_buses), p_mw=0.0, q_mvar=0.0)
    return net


def _solve(pp, net, warm: bool) -> bool:
    """Whether Newton-Raphson converges on the net's loads: from the last hour's solution if ``warm`` (recycling
    its admittance matrix), else from a flat start. numba is not used (nor installed)."""
    try:
        pp.runpp(net, init="results" if warm else "flat", recycle=_RECYCLE if warm else None, numba=False,
                 check_connectivity=False, voltage_depend_loads=False)
    except pp.LoadflowNotConverged:
        return False
    return True


def _ac_results(net) -> dict[str, np.ndarray | float]:
    line = net.res_line
    return {"v": net.res_bus.vm_pu.to_numpy(), "p_from": line.p_from_mw.to_numpy(),
            "q_from": line.q_from_mvar.to_numpy(), "p_to": line.p_to_mw.to_numpy(),
            "q_to": line.q_to_mvar.to_numpy(), "losses": float(line.pl_mw.sum()),
            "substation": float(net.res_ext_grid.p_mw.iat[0])}


def _hour_check(network: Network, hour: int, ac, ldf_p: np.ndarray, ldf_v: np.ndarray, margin: float) -> HourCheck:
    if ac is None:
        nan = math.nan
        return HourCheck(hour=hour, converged=False, v_min_pu=nan, v_min_bus="", v_max_pu=nan, v_max_bus="",
                         max_loading=nan, max_loading_line="", voltage_error_pu=nan, flow_error_mw=nan,
                         losses_mw=nan, substation_mw=nan, violations=(NOT_CONVERGED,), margin=margin,
                         v_pu=(nan,) * network.n_buses, loading=(nan,) * network.n_lines)
    v = ac["v"]
    # the sending end is where active power enters the line: its substation end unless the flow runs back
    sending = np.where(ac["p_from"] >= 0, np.hypot(ac["p_from"], ac["q_from"]), np.hypot(ac["p_to"], ac["q_to"]))
    loading = sending / network.s_max_mva
    low, high, worst = int(v.argmin()), int(v.argmax()), int(loading.argmax())
    return HourCheck(hour=hour, converged=True, v_min_pu=float(v[low]), v_min_bus=network.buses[low],
                     v_max_pu=float(v[high]), v_max_bus=network.buses[high], max_loading=float(loading[worst]),
                     max_loading_line=network.line_names[worst],
                     voltage_error_pu=float(np.abs(ldf_v - v).max()),
                     flow_error_mw=float(np.abs(ldf_p - ac["p_from"]).max()),
                     losses_mw=ac["losses"], substation_mw=ac["substation"],
                     violations=_violations(network, v, loading), margin=margin,
                     v_pu=tuple(v.tolist()), loading=tuple(loading.tolist()))


def _violations(network: Network, v: np.ndarray, loading: np.ndarray) -> tuple[str, ...]:
    """Every limit broken by more than VIOLATION_TOLERANCE, in the network's bus order then line order:
    "undervoltage 17 0.9491<0.95", "overvoltage 4 1.0512>1.05", "overload 2-3 104.2%"."""
    names, tol = network.buses, VIOLATION_TOLERANCE
    out = [f"undervoltage {names[b]} {v[b]:.4f}<{network.v_min[b]:g}" for b in np.flatnonzero(v < network.v_min - tol)]
    out += [f"overvoltage {names[b]} {v[b]:.4f}>{network.v_max[b]:g}" for b in np.flatnonzero(v > network.v_max + tol)]
    out += [f"overload {network.line_names[l]} {100 * loading[l]:.1f}%" for l in np.flatnonzero(loading > 1 + tol)]
    return tuple(out)
