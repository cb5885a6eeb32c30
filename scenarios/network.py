"""Radial distribution feeders as data: buses, lines, voltage limits, the substation and the fixed loads per hour.

A ``Network`` is what the DMO clears on instead of the copper plate (docs/network.md): a radial feeder whose lines
have a series resistance and reactance (ohm) and a thermal limit (MVA), whose buses have voltage limits (p.u.) and
fixed non-microgrid loads (MW, Mvar, times an hourly profile), and whose substation bus is where the DMO trades
with the ISO. Built in: the IEEE 33-bus feeder of Baran and Wu (1989), taken from pandapower's ``case33bw``, and
``feeder5``, a five-bus feeder for tests. A user's feeder is a TOML file (docs/network.md) or a pandapower JSON, read
as data (``scenarios.pandapower_json``).

Everything here is validated once, on load, with one line naming the file and what is wrong: a meshed or
disconnected feeder, a line of zero impedance, a bus that does not exist, limits that are not limits, a name or a
number the DMO's clearing and messages cannot carry. What loads is what a run can clear on.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from scenarios import exact
from scenarios.case import DATA_DIR, read_toml
from scenarios.horizon import HOURS
from scenarios.pandapower_json import Table, net_tables, read_tables

S_BASE_MVA = 1.0  # the per-unit power base: MW and Mvar are per unit as they are
# Lines a feeder file gives no rating get RATING_MARGIN times the nominal apparent power of the fixed load
# downstream of them (at the profile's peak), and never less than MIN_RATING_MVA (docs/network.md, "Line ratings").
RATING_MARGIN = 1.5
MIN_RATING_MVA = 0.5
UNRATED_KA = 9_999.0  # pandapower's way of saying "no rating" (case33bw gives 99,999 kA): at or above it, unrated
V_MIN, V_MAX = 0.95, 1.05  # p.u., a bus's limits when its file gives none (ANSI C84.1 range A)
MAX_BUSES = 5_000
MAX_NAME_LENGTH = 64  # characters of a feeder's name and of each bus's: what the DMO's messages carry of them
# The bounds of a feeder's numbers (docs/network.md, "Limits"): wider than a distribution feeder needs, and narrow
# enough that every product and sum the clearing, its messages and the AC check make of them stays finite and within
# what the LP solver resolves (a load of 1e308 MW is a finite number; twice it is not).
KV_RANGE = (0.1, 1_000.0)  # base_kv, kV
MAX_BUS_MW = 10_000.0  # |p_mw| and |q_mvar| of a bus's fixed load
MAX_LOAD_TAN = 10.0  # |q_mvar| / p_mw of a bus whose fixed load consumes P: the clearing sheds its Q with its P
MIN_LINE_OHM, MAX_LINE_OHM = 1e-6, 10_000.0  # a line's r_ohm + x_ohm at least, and each of them at most
MAX_LINE_MVA = 1_000_000.0  # a line's s_max_mva
MAX_MULTIPLIER = 10.0  # each of load_profile's multipliers, load_scale and rating_margin
MIN_POWER_FACTOR = 0.5  # power_factor: a microgrid draws at most tan(acos(0.5)) = 1.73 Mvar per MW
# A typical residential feeder's day, peak 1.0 at 19:00 (hour 20), night trough 0.55: the shape of every bus's
# fixed load unless the network file gives its own ``load_profile``.
LOAD_PROFILE = (0.62, 0.57, 0.55, 0.55, 0.56, 0.60, 0.68, 0.76, 0.80, 0.80, 0.79, 0.78,
                0.77, 0.76, 0.76, 0.78, 0.83, 0.91, 0.98, 1.00, 0.97, 0.89, 0.78, 0.68)
_TOP = ("name", "base_kv", "substation", "v_min", "v_max", "load_profile", "load_scale", "rating_margin",
        "power_factor", "buses", "lines")
_BUS = ("name", "p_mw", "q_mvar", "v_min", "v_max")
_LINE = ("from", "to", "r_ohm", "x_ohm", "s_max_mva")


class NetworkError(ValueError):
    """A network that cannot be used; the message names the file (or the network) and what is wrong."""


@dataclass(frozen=True, eq=False)
class Network:
    """A radial feeder, checked. Buses are indexed 0..n-1 in the order given, lines 0..n-2 and oriented away from
    the substation: line l runs from ``parent[l]`` to ``child[l]``, and ``line_to[b]`` is the line feeding bus b
    (-1 at the substation). Arrays are read-only.

    ``r_ohm``, ``x_ohm``: series impedance per line; ``s_max_mva``: thermal limit per line; ``v_min``, ``v_max``:
    voltage limits per bus (p.u.; the substation is held at ``v_substation``); ``load_p_mw``, ``load_q_mvar``:
    nominal fixed load per bus, which ``fixed_p``/``fixed_q`` give per hour (times ``load_profile`` and
    ``load_scale``); ``power_factor``: every microgrid's, Q = tan(phi) P (docs/network.md).
    """

    name: str
    base_kv: float
    buses: tuple[str, ...]
    root: int
    parent: np.ndarray
    child: np.ndarray
    r_ohm: np.ndarray
    x_ohm: np.ndarray
    s_max_mva: np.ndarray
    v_min: np.ndarray
    v_max: np.ndarray
    load_p_mw: np.ndarray
    load_q_mvar: np.ndarray
    load_profile: tuple[float, ...] = LOAD_PROFILE
    load_scale: float = 1.0
    power_factor: float = 1.0
    v_substation: float = 1.0

    @property
    def substation(self) -> str:
        """The substation bus's name: the DMO's point of exchange with the ISO."""
        return self.buses[self.root]

    @property
    def n_buses(self) -> int:
        return len(self.buses)

    @property
    def n_lines(self) -> int:
        return len(self.child)

    @cached_property
    def index(self) -> dict[str, int]:
        """Bus name -> bus index."""
        return {b: i for i, b in enumerate(self.buses)}

    @cached_property
    def line_to(self) -> np.ndarray:
        out = np.full(self.n_buses, -1)
        out[self.child] = np.arange(self.n_lines)
        return _frozen(out)

    @cached_property
    def downstream(self) -> np.ndarray:
        """(lines x buses) 0/1: whether bus b lies at or below line l's child, i.e. whether a load at b flows
        through l. It is the radial feeder's sensitivity of every line flow to every bus's load (LinDistFlow)."""
        d = np.zeros((self.n_lines, self.n_buses))
        for b in range(self.n_buses):  # walk each bus up to the substation: O(n depth), once per network
            line = self.line_to[b]
            while line >= 0:
                d[line, b] = 1.0
                line = self.line_to[self.parent[line]]
        return _frozen(d)

    @property
    def tan_phi(self) -> float:
        """Q/P of every microgrid's exchange at its power factor (lagging: a microgrid importing P draws Q)."""
        return math.tan(math.acos(self.power_factor))

    @property
    def z_base_ohm(self) -> float:
        return self.base_kv ** 2 / S_BASE_MVA

    @property
    def r_pu(self) -> np.ndarray:
        return self.r_ohm / self.z_base_ohm

    @property
    def x_pu(self) -> np.ndarray:
        return self.x_ohm / self.z_base_ohm

    @cached_property
    def fixed_p(self) -> np.ndarray:
        """(24 x buses) fixed non-microgrid load, MW: nominal x profile x scale."""
        return _frozen(np.outer(np.asarray(self.load_profile) * self.load_scale, self.load_p_mw))

    @cached_property
    def fixed_q(self) -> np.ndarray:
        """(24 x buses) fixed non-microgrid load, Mvar."""
        return _frozen(np.outer(np.asarray(self.load_profile) * self.load_scale, self.load_q_mvar))

    @cached_property
    def line_names(self) -> tuple[str, ...]:
        """Each line as "from-to", from the substation's side, in the feeder's line order."""
        return tuple(f"{self.buses[a]}-{self.buses[b]}" for a, b in zip(self.parent, self.child))

    def lindistflow(self, p: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """LinDistFlow's line flows and bus voltages for loads ``p`` (MW) and ``q`` (Mvar) per bus (shape (...,
        buses), positive consumption, the substation's ignored): P = D p and Q = D q on each line away from the
        substation (..., lines), and V (p.u., (..., buses)) = sqrt(v_substation^2 - 2 D'(r P + x Q)): U = V^2
        drops by 2 (r P + x Q) along every line of a bus's path (Baran and Wu 1989). Losses are neglected."""
        flow_p, flow_q = exact.masked_sums(self.downstream, p), exact.masked_sums(self.downstream, q)
        u = self.v_substation ** 2 - 2 * exact.masked_sums(self.downstream.T, flow_p * self.r_pu + flow_q * self.x_pu)
        return flow_p, flow_q, np.sqrt(np.maximum(u, 0.0))

    def bus_of(self, bus: object, where: str = "bus") -> int:
        """The index of a bus named by a string or integer; NetworkError naming the network if there is none, or
        if it is the substation (a microgrid trades through the feeder, not at the ISO's bus)."""
        name = str(bus) if isinstance(bus, (str, int)) and not isinstance(bus, bool) else None
        if name not in self.index:
            raise NetworkError(f"{where}: no bus {bus!r} in network {self.name} (buses: {_sample(self.buses)})")
        if self.index[name] == self.root:
            raise NetworkError(f"{where}: bus {name} is network {self.name}'s substation; place microgrids on "
                               "the feeder's other buses")
        return self.index[name]


def voltage_band(network: Network, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Every bus's voltage limits drawn in by ``margin`` p.u. at each end: the band the clearing holds LinDistFlow's
    voltages in, room for what it neglects (docs/network.md, "The AC check"). NetworkError, one line, if the margin
    is negative or leaves a bus (other than the substation, which is held at its voltage) no band."""
    margin = _number(margin, "voltage margin", network.name)
    lo, hi = network.v_min + margin, network.v_max - margin
    narrow = np.flatnonzero((lo >= hi) & (np.arange(network.n_buses) != network.root))
    if margin < 0 or narrow.size:
        raise NetworkError(f"network {network.name}: a voltage margin must be >= 0 p.u. and leave each bus a "
                           f"voltage band, got {margin:g}"
                           + (f" (bus {network.buses[narrow[0]]} has none left)" if narrow.size else ""))
    return lo, hi


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _sample(names, k: int = 6) -> str:
    return ", ".join(names[:k]) + (f", ... ({len(names)} buses)" if len(names) > k else "")


# --- building and checking ---------------------------------------------------------------------------------------

def build(name: str, base_kv: float, buses: list[dict], lines: list[dict], substation: str, *,
          load_profile=LOAD_PROFILE, load_scale: float = 1.0, rating_margin: float = RATING_MARGIN,
          power_factor: float = 1.0, v_min: float = V_MIN, v_max: float = V_MAX) -> Network:
    """A checked ``Network`` from plain rows: ``buses`` [{name, p_mw, q_mvar, v_min?, v_max?}], ``lines``
    [{from, to, r_ohm, x_ohm, s_max_mva?}] (either direction). NetworkError names what is wrong: every name and
    number is checked against what the DMO's clearing and messages can carry (docs/network.md, "Limits")."""
    name = _label(name, "the network's name")
    _within(base_kv, "base_kv", name, *KV_RANGE)
    _within(power_factor, "power_factor", name, MIN_POWER_FACTOR, 1.0)
    _within(load_scale, "load_scale", name, 0.0, MAX_MULTIPLIER, above=True)
    _within(rating_margin, "rating_margin", name, 0.0, MAX_MULTIPLIER, above=True)
    profile = _profile(load_profile, name)
    if not 2 <= len(buses) <= MAX_BUSES:
        raise NetworkError(f"network {name}: {len(buses)} buses; a feeder has 2..{MAX_BUSES}")
    names = [_label(b["name"], f"bus {k + 1}'s name", name) for k, b in enumerate(buses)]
    if len(set(names)) != len(names):
        dup = sorted(n for n in set(names) if names.count(n) > 1)[0]
        raise NetworkError(f"network {name}: bus {dup} is listed twice")
    index = {b: i for i, b in enumerate(names)}
    if str(substation) not in index:
        raise NetworkError(f"network {name}: substation {substation!r} is not one of its buses ({_sample(names)})")
    root = index[str(substation)]
    lo = np.array([_number(b.get("v_min", v_min), f"bus {n} v_min", name) for n, b in zip(names, buses)])
    hi = np.array([_number(b.get("v_max", v_max), f"bus {n} v_max", name) for n, b in zip(names, buses)])
    bad = np.flatnonzero(~((0.5 <= lo) & (lo < hi) & (hi <= 1.5)))
    if bad.size:
        raise NetworkError(f"network {name}: bus {names[bad[0]]}: voltage limits {lo[bad[0]]:g}..{hi[bad[0]]:g} p.u. "
                           "are not limits (need 0.5 <= v_min < v_max <= 1.5)")
    p, q = (np.array([_within(b.get(f, 0.0), f"bus {n} {f}", name, -MAX_BUS_MW, MAX_BUS_MW)
                      for n, b in zip(names, buses)]) for f in ("p_mw", "q_mvar"))
    if p[root] or q[root]:
        raise NetworkError(f"network {name}: the substation bus {names[root]} carries no fixed load")
    steep = np.flatnonzero((p > 0) & (np.abs(q) > MAX_LOAD_TAN * p))
    if steep.size:
        b = steep[0]
        raise NetworkError(f"network {name}: bus {names[b]}: a fixed load of {p[b]:g} MW and {q[b]:g} Mvar; where it "
                           f"consumes P, |q_mvar| is at most {MAX_LOAD_TAN:g} x p_mw (a load shed sheds its Q with it)")

    if len(lines) != len(names) - 1:
        what = "meshed" if len(lines) > len(names) - 1 else "not connected"
        raise NetworkError(f"network {name}: {len(lines)} lines for {len(names)} buses: a radial feeder has one "
                           f"line fewer than buses (this one is {what})")
    ends, r, x, s = [], [], [], []
    for k, line in enumerate(lines):
        a, b = (str(line.get(end)) for end in ("from", "to"))
        where = f"line {k + 1} ({a[:MAX_NAME_LENGTH]}-{b[:MAX_NAME_LENGTH]})"
        for end in (a, b):
            if end not in index:
                raise NetworkError(f"network {name}: {where}: no bus {end[:MAX_NAME_LENGTH]!r} ({_sample(names)})")
        if a == b:
            raise NetworkError(f"network {name}: {where}: a line from a bus to itself")
        rk, xk = (_within(line.get(f, None), f"{where} {f}", name, 0.0, MAX_LINE_OHM) for f in ("r_ohm", "x_ohm"))
        if rk + xk < MIN_LINE_OHM:
            raise NetworkError(f"network {name}: {where}: impedance {rk:g} + j{xk:g} ohm; a line needs r + x >= "
                               f"{MIN_LINE_OHM:g} ohm (join the buses instead)")
        rating = line.get("s_max_mva")
        s.append(math.nan if rating is None else _within(rating, f"{where} s_max_mva", name, 0.0, MAX_LINE_MVA,
                                                          above=True))
        ends.append((index[a], index[b]))
        r.append(rk)
        x.append(xk)
    parent, child = _orient(ends, root, len(names), name, names)
    net = Network(name=name, base_kv=float(base_kv), buses=tuple(names), root=root,
                  parent=_frozen(np.array(parent)), child=_frozen(np.array(child)),
                  r_ohm=_frozen(np.array(r)), x_ohm=_frozen(np.array(x)), s_max_mva=np.array(s), v_min=_frozen(lo), v_max=_frozen(hi),
                  load_p_mw=_frozen(p), load_q_mvar=_frozen(q), load_profile=profile,
                  load_scale=float(load_scale), power_factor=float(power_factor))
    unrated = np.isnan(net.s_max_mva)
    peak = max(profile) * load_scale
    downstream_s = np.hypot(exact.masked_sums(net.downstream, p), exact.masked_sums(net.downstream, q)) * peak
    net.s_max_mva[unrated] = np.maximum(rating_margin * downstream_s[unrated], MIN_RATING_MVA)
    _frozen(net.s_max_mva)
    return net


def _orient(ends, root: int, n: int, name: str, names) -> tuple[list[int], list[int]]:
    """Each line as (parent, child) away from the substation, lines kept in their given order; NetworkError if
    a bus cannot be reached (then, with n - 1 lines, the feeder also has a loop)."""
    adjacent: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for k, (a, b) in enumerate(ends):
        adjacent[a].append((b, k))
        adjacent[b].append((a, k))
    parent_of = {root: -1}
    child = [-1] * len(ends)  # line k's end away from the substation
    stack = [root]
    while stack:
        bus = stack.pop()
        for other, k in adjacent[bus]:
            if other not in parent_of:
                parent_of[other] = bus
                child[k] = other
                stack.append(other)
    if len(parent_of) < n:
        lost = next(names[b] for b in range(n) if b not in parent_of)
        raise NetworkError(f"network {name}: bus {lost} cannot be reached from the substation and the lines form a "
                           "loop: a feeder must be radial (a tree)")
    return [parent_of[c] for c in child], child


def _label(value, what: str, network: str | None = None) -> str:
    """A feeder's or a bus's name: a string (or an integer, as pandapower numbers its buses) of 1..MAX_NAME_LENGTH
    printable characters, as the DMO's messages carry it; NetworkError, one line, otherwise."""
    text = str(value) if isinstance(value, (str, int)) and not isinstance(value, bool) else None
    if text is None or not 1 <= len(text) <= MAX_NAME_LENGTH or not text.isprintable():
        shown = _shown(value) if text is None or len(text) <= MAX_NAME_LENGTH else f"{text[:MAX_NAME_LENGTH]!r}..."
        size = "" if text is None else f" ({len(text)} characters)"
        raise NetworkError(("" if network is None else f"network {network}: ") + f"{what} {shown}{size}: a name is "
                           f"1..{MAX_NAME_LENGTH} printable characters, as the DMO's messages carry it")
    return text


def _number(value, what: str, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise NetworkError(f"network {name}: {what} must be a finite number, got {_shown(value)}")
    return float(value)


def _shown(value) -> str:
    """A value a file gave, as an error line shows it: its repr, cut short."""
    text = repr(value)
    return text if len(text) <= 80 else f"{text[:80]}..."


def _within(value, what: str, name: str, lo: float, hi: float, above: bool = False) -> float:
    """``value`` as a finite number in lo..hi (above lo, with ``above``), else NetworkError naming ``what``."""
    value = _number(value, what, name)
    if not (lo < value if above else lo <= value) or value > hi:
        most = f" and <= {hi:,g}" if hi < math.inf else ""
        raise NetworkError(f"network {name}: {what} must be {'>' if above else '>='} {lo:,g}{most}, got {value:g}")
    return value


def _profile(profile, name: str) -> tuple[float, ...]:
    if isinstance(profile, (str, bytes)) or not hasattr(profile, "__len__") or len(profile) != HOURS:
        raise NetworkError(f"network {name}: load_profile must list {HOURS} hourly multipliers")
    return tuple(_within(v, f"load_profile hour {h + 1}", name, 0.0, MAX_MULTIPLIER) for h, v in enumerate(profile))


# --- files ----------------------------------------------------------------------------------------------------

def parse_network(data: dict, name: str) -> Network:
    """A network from the dict of a network TOML (docs/network.md); NetworkError names ``name`` and the field."""
    unknown = sorted(set(data) - set(_TOP))
    if unknown:
        raise NetworkError(f"network {name}: unknown field {unknown[0]!r} (fields: {', '.join(_TOP)})")
    for part, fields in (("buses", _BUS), ("lines", _LINE)):
        rows = data.get(part)
        if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
            raise NetworkError(f"network {name}: {part} must be a list of tables ([[{part}]])")
        for k, row in enumerate(rows):
            extra = sorted(set(row) - set(fields))
            if extra:
                raise NetworkError(f"network {name}: {part}[{k}].{extra[0]}: unknown field (fields: {', '.join(fields)})")
            if part == "buses" and "name" not in row:
                raise NetworkError(f"network {name}: buses[{k}].name: missing field")
    for key in ("base_kv", "substation"):
        if key not in data:
            raise NetworkError(f"network {name}: {key}: missing field")
    options = {k: data[k] for k in ("load_profile", "load_scale", "rating_margin", "power_factor", "v_min", "v_max")
               if k in data}
    return build(data.get("name", name), data["base_kv"], data["buses"], data["lines"], str(data["substation"]),
                 **options)


def from_pandapower(net, name: str, **options) -> Network:
    """A network from a pandapower net in memory (``from_tables`` of its tables)."""
    return from_tables(net_tables(net), name, **options)


def from_tables(tables: Mapping[str, Table], name: str, **options) -> Network:
    """A network from a pandapower net's tables (``scenarios.pandapower_json``), as docs/network.md reads them: the
    buses in service (named by their index, all at one voltage: ``base_kv``), the one external grid in service (its
    bus the substation), the lines in service (r and x per km times length over parallel circuits; ``max_i_ka`` NaN
    or at least ``UNRATED_KA`` is no rating), loads less static generators in service, times their scaling, summed
    per bus, and the buses' voltage limits where given. Transformers are refused (a feeder here is one voltage
    level), and so is an element in service at a bus that is not."""
    if len(tables["trafo"]) or len(tables["trafo3w"]):
        raise NetworkError(f"network {name}: has transformers; a feeder here is one voltage level")
    bus = tables["bus"]
    live = {}  # bus index -> its row, for the buses in service, in the table's order
    for k, i in enumerate(bus.index):
        if isinstance(i, bool) or not isinstance(i, int):
            raise NetworkError(f"network {name}: table bus: row {k + 1} is labelled {_shown(i)}, not a bus number")
        if _flag(bus.columns["in_service"][k], f"bus {i} in_service", name):
            live[i] = k
    if not 2 <= len(live) <= MAX_BUSES:
        raise NetworkError(f"network {name}: {len(live)} buses in service; a feeder has 2..{MAX_BUSES}")
    levels = {_number(bus.columns["vn_kv"][k], f"bus {i} vn_kv", name) for i, k in live.items()}
    if len(levels) != 1:
        raise NetworkError(f"network {name}: buses at several voltages {sorted(levels)} kV; a feeder here is one level")
    kv = levels.pop()
    p, q = dict.fromkeys(live, 0.0), dict.fromkeys(live, 0.0)
    for table, sign in (("load", 1.0), ("sgen", -1.0)):
        for k, row in _in_service(tables[table], table, name):
            at = _at_bus(row["bus"], f"{table} {k}", live, name)
            scaling = _within(row["scaling"], f"{table} {k} scaling", name, 0.0, MAX_MULTIPLIER)
            p[at] += sign * _number(row["p_mw"], f"{table} {k} p_mw", name) * scaling
            q[at] += sign * _number(row["q_mvar"], f"{table} {k} q_mvar", name) * scaling
    buses = []
    for i, k in live.items():
        row = {"name": str(i), "p_mw": p[i], "q_mvar": q[i]}
        for col, key in (("min_vm_pu", "v_min"), ("max_vm_pu", "v_max")):
            value = bus.columns[col][k] if col in bus.columns else math.nan
            if not (isinstance(value, float) and math.isnan(value)):
                row[key] = value
        buses.append(row)
    grids = list(_in_service(tables["ext_grid"], "ext_grid", name))
    if len(grids) != 1:
        raise NetworkError(f"network {name}: needs exactly one external grid (the substation), has {len(grids)}")
    root = _at_bus(grids[0][1]["bus"], f"ext_grid {grids[0][0]}", live, name)
    buses[list(live).index(root)].update(p_mw=0.0, q_mvar=0.0, v_min=0.5, v_max=1.5)  # held at its set point
    lines = []
    for k, ln in _in_service(tables["line"], "line", name):
        where = f"line {k}"
        length = _within(ln["length_km"], f"{where} length_km", name, 0.0, math.inf, above=True)
        parallel = ln["parallel"]
        if isinstance(parallel, bool) or not isinstance(parallel, (int, float)) or not (
                parallel >= 1 and float(parallel).is_integer()):
            raise NetworkError(f"network {name}: {where} parallel must be a whole number of circuits >= 1, got "
                               f"{_shown(parallel)}")
        factor = length / parallel
        ends = (str(_at_bus(ln[end], where, live, name)) for end in ("from_bus", "to_bus"))
        row = dict(zip(("from", "to"), ends),
                   r_ohm=_number(ln["r_ohm_per_km"], f"{where} r_ohm_per_km", name) * factor,
                   x_ohm=_number(ln["x_ohm_per_km"], f"{where} x_ohm_per_km", name) * factor)
        rating = ln["max_i_ka"]  # NaN, pandas' "not given", leaves the line unrated as UNRATED_KA does
        if not (isinstance(rating, float) and math.isnan(rating)) and _number(rating, f"{where} max_i_ka",
                                                                                name) < UNRATED_KA:
            row["s_max_mva"] = math.sqrt(3) * kv * rating * parallel
        lines.append(row)
    return build(name, kv, buses, lines, str(root), **options)


def _in_service(table: Table, what: str, name: str):
    """(row label, row as a dict of the columns read) of each row of ``table`` in service."""
    for k, label in enumerate(table.index):
        row = {c: values[k] for c, values in table.columns.items()}
        label = str(label)[:MAX_NAME_LENGTH]  # a row's label in messages: pandapower's are numbers
        if _flag(row["in_service"], f"{what} {label} in_service", name):
            yield label, row


def _flag(value, what: str, name: str) -> bool:
    if not isinstance(value, bool):
        raise NetworkError(f"network {name}: {what} must be true or false, got {_shown(value)}")
    return value


def _at_bus(value, what: str, live: Mapping[int, int], name: str) -> int:
    """The bus an element in service is at: a bus in service, else NetworkError."""
    bus = int(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and float(value).is_integer() \
        else None
    if bus not in live:
        raise NetworkError(f"network {name}: {what} is in service at bus {_shown(value)}, which is not a bus in "
                           "service")
    return bus


@contextmanager
def quiet_pandapower():
    """While pandapower is imported or run: its log records below ERROR and its Python warnings are dropped, so
    none of its chatter reaches a role's stderr (on import it logs that plotly is missing, at INFO); its errors
    still log and its exceptions still raise."""
    logger = logging.getLogger("pandapower")
    level = logger.level
    logger.setLevel(max(level, logging.ERROR))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        logger.setLevel(level)


def synthetic(n: int, seed: int = 0, **options) -> Network:
    """A random radial feeder of ``n`` buses for benchmarks: bus b hangs off one of the buses 3b/4..b-1 (about log(n)/log(4/3) deep), lines of
    0.01..0.05 + j0.01..0.04 ohm at 12.47 kV, 2..10 kW per bus at power factor 0.9, limits 0.9..1.1 p.u."""
    rng = np.random.default_rng([seed, n])
    parent = [int(rng.integers(b * 3 // 4, b)) for b in range(1, n)]
    p = rng.uniform(0.002, 0.01, n)
    p[0] = 0.0
    buses = [{"name": str(b), "p_mw": p[b], "q_mvar": p[b] * 0.4843, "v_min": 0.9, "v_max": 1.1} for b in range(n)]
    lines = [{"from": str(a), "to": str(b + 1), "r_ohm": r, "x_ohm": x}
             for b, (a, r, x) in enumerate(zip(parent, rng.uniform(0.01, 0.05, n - 1), rng.uniform(0.01, 0.04, n - 1)))]
    return build(f"synthetic{n}", 12.47, buses, lines, "0", **options)


def ieee33(**options) -> Network:
    """The IEEE 33-bus feeder of Baran and Wu (1989), as pandapower's ``case33bw``: 12.66 kV, 32 lines in service
    (its 5 tie switches open), 3.715 MW / 2.300 Mvar of load, bus limits 0.9..1.1 p.u.; lines rated by the rule."""
    with quiet_pandapower():
        import pandapower.networks as pn  # 1 s to import: only when this feeder is asked for

        case = pn.case33bw()
    return from_pandapower(case, "ieee33", **options)


NETWORKS = {"ieee33": ieee33, "ieee69": lambda **options: _toml(DATA_DIR / "ieee69.toml", options),
            "mantovani136": lambda **options: _toml(DATA_DIR / "mantovani136.toml", options),
            "feeder5": lambda **options: _toml(DATA_DIR / "feeder5.toml", options)}


def load_network(source: str | Path, **options) -> Network:
    """A built-in network by name (``NETWORKS``), or a file: ``*.json`` a pandapower net (read as data,
    ``scenarios.pandapower_json``), anything else a network TOML. ``options`` (load_scale, rating_margin, ...)
    override the file's. NetworkError names what is wrong."""
    if isinstance(source, str) and source in NETWORKS:
        return NETWORKS[source](**options)
    path = Path(source)
    if path.suffix.lower() == ".json":
        tables = read_tables(path, NetworkError)
        try:
            return from_tables(tables, path.stem, **options)
        except NetworkError as exc:
            raise NetworkError(f"{path}: {exc}") from None
    if not path.suffix and not path.exists():
        raise NetworkError(f"unknown network {source!r}: not a built-in ({', '.join(NETWORKS)}) nor a file")
    return _toml(path, options)


def _toml(path: Path, options: dict) -> Network:
    data = read_toml(path, "network", NetworkError)
    try:
        return parse_network({**data, **options}, path.stem)
    except NetworkError as exc:
        raise NetworkError(f"{path}: {exc}") from None
