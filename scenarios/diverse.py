"""Diverse microgrids drawn from one seed: from a base case (the paper's), each member's size, load shape, unit mix,
renewables, storage and tie to the grid, every one a valid case its agent can schedule (docs/agent.md, "Generated
fleets").

Member i (1-based) draws ``DRAWS_PER_MEMBER + 3 x units`` uniforms and its realised-day seed from its own stream
``[seed, i]``, so a larger fleet extends a smaller one; what the uniforms become is computed for the whole fleet at
once (``draw``, ``shaped_loads``, ``drawn_cases``), pure functions of the uniforms and the base.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from scenarios.case import Case, CaseError, load_case, parse_case
from scenarios.days import check_seed
from scenarios.fleet import MAX_MEMBERS, FleetMember
from scenarios.horizon import HOURS

# What is drawn, from what range; docs/agent.md ("Generated fleets") says why each range. Ratios are to the
# member's own peak fixed load; the paper's case has a 17.0 MW peak.
SIZE_RANGE = (1 / 3, 3.0)        # log-uniform: the member's daily fixed-load energy over the base's
# name: (hours the base's forecast is rolled, contrast around its mean); contrast > 1 deepens peak and valley
LOAD_SHAPES = {"paper": (0, 1.0), "residential": (3, 1.4), "commercial": (-4, 1.6), "industrial": (0, 0.3)}
ROLL_JITTER = (-1, 0, 1)         # hours added to the shape's roll
CONTRAST_JITTER = (0.85, 1.15)   # times the shape's contrast
UNIT_PRESENT = 0.6               # chance each unit of the base is in the member's mix (at least one always is)
UNIT_WEIGHT = (0.7, 1.3)         # times the base unit's share of the dispatchable capacity
UNIT_COST = (0.9, 1.1)           # times the base unit's marginal cost
CAPACITY_RANGE = (0.8, 1.1)      # dispatchable capacity; the paper's 16 MW is 0.94
RENEWABLE_RANGE = (0.05, 0.6)    # wind and solar capacity; the paper's 2.5 MW is 0.15
WIND_SHARE = (-0.2, 1.2)         # of the renewable capacity, clipped to [0, 1]: 1 in 7 all solar, 1 in 7 all wind
# kind: (chance, range of the storage's size over the base's at the member's size); the base's storage otherwise
STORAGE_KINDS = {"none": (0.25, (0.0, 0.0)), "small": (0.4, (0.3, 1.0)), "large": (0.35, (1.0, 3.0))}
TIE_RANGE = (0.7, 1.2)           # P_M^max; the paper's 16 MW is 0.94
DRAWS_PER_MEMBER = 10            # uniforms of a member besides its three per unit of the base
DIGITS = 4                       # MW, MWh and $ written to the case, rounded: 0.1 kW


@dataclass(frozen=True)
class Draws:
    """What the uniforms of N members became: arrays over the members (and over the base's units, G)."""

    size: np.ndarray        # (N,) energy over the base's
    shape: np.ndarray       # (N,) index into LOAD_SHAPES
    roll: np.ndarray        # (N,) hours
    contrast: np.ndarray    # (N,)
    units: np.ndarray       # (N, G) bool: the base's unit is in the mix
    weight: np.ndarray      # (N, G) share of the dispatchable capacity (rows sum to 1)
    cost: np.ndarray        # (N, G) times the base unit's cost
    capacity: np.ndarray    # (N,) dispatchable capacity over peak fixed load
    renewable: np.ndarray   # (N,) wind and solar capacity over peak fixed load
    wind: np.ndarray        # (N,) wind's share of it
    storage: np.ndarray     # (N,) index into STORAGE_KINDS
    storage_size: np.ndarray  # (N,) the storage over the base's, at the member's size (0: none)
    tie: np.ndarray         # (N,) P_M^max over peak fixed load


def _between(u: np.ndarray, bounds: tuple[float, float]) -> np.ndarray:
    return bounds[0] + u * (bounds[1] - bounds[0])


def draw(u: np.ndarray, units: int) -> Draws:
    """The draws of N members from their uniforms ``u`` (N, DRAWS_PER_MEMBER + 3 x ``units``)."""
    v, present_u, weight_u, cost_u = np.split(u, DRAWS_PER_MEMBER + np.arange(3) * units, axis=1)
    n = len(u)
    shape = np.minimum((v[:, 1] * len(LOAD_SHAPES)).astype(int), len(LOAD_SHAPES) - 1)
    rolls, contrasts = np.array(list(LOAD_SHAPES.values())).T
    jitter = np.array(ROLL_JITTER)[np.minimum((v[:, 2] * len(ROLL_JITTER)).astype(int), len(ROLL_JITTER) - 1)]
    present = present_u < UNIT_PRESENT
    # a member that drew no unit keeps the one it came nearest to drawing
    present[np.arange(n), np.argmin(present_u, axis=1)] |= ~present.any(axis=1)
    weight = np.where(present, _between(weight_u, UNIT_WEIGHT), 0.0)
    chances = np.cumsum([chance for chance, _ in STORAGE_KINDS.values()])
    storage = np.minimum(np.searchsorted(chances / chances[-1], v[:, 6], side="right"), len(STORAGE_KINDS) - 1)
    low, high = np.array([bounds for _, bounds in STORAGE_KINDS.values()]).T
    return Draws(
        size=np.exp(_between(v[:, 0], np.log(SIZE_RANGE))), shape=shape, roll=(rolls[shape] + jitter).astype(int),
        contrast=contrasts[shape] * _between(v[:, 3], CONTRAST_JITTER), units=present,
        weight=weight, cost=_between(cost_u, UNIT_COST), capacity=_between(v[:, 4], CAPACITY_RANGE),
        renewable=_between(v[:, 5], RENEWABLE_RANGE), wind=np.clip(_between(v[:, 7], WIND_SHARE), 0.0, 1.0),
        storage=storage, storage_size=low[storage] + v[:, 8] * (high[storage] - low[storage]),
        tie=_between(v[:, 9], TIE_RANGE))


def shaped_loads(base: np.ndarray, d: Draws) -> np.ndarray:
    """(N, 24) fixed-load forecasts: the base's rolled by each member's roll, its contrast around the base's mean
    scaled by the member's, times its size (so a member's daily energy is its size times the base's)."""
    hours = np.arange(HOURS)
    rolled = base[(hours[None, :] - d.roll[:, None]) % HOURS]
    mean = base.mean()
    return np.maximum(d.size[:, None] * (mean + d.contrast[:, None] * (rolled - mean)), 0.0)


def _rounded(x) -> np.ndarray:
    return np.round(np.asarray(x, dtype=float), DIGITS)


def drawn_cases(base: Case, d: Draws, names: list[str], seed: int) -> list[Case]:
    """The members' cases (``names``, in order), built from the draws ``d`` and the ``base``: each validated as a case
    file is and checked schedulable (``schedulable_problems``); a CaseError names a member that is not."""
    loads = _rounded(shaped_loads(np.asarray(base.fixed_load.forecast, float), d))
    peak = loads.max(axis=1)
    b_pmax = base.unit_array("p_max")
    p_max = _rounded(d.capacity[:, None] * peak[:, None] * d.weight / d.weight.sum(axis=1, keepdims=True))
    factor = p_max / b_pmax  # each unit's size over the base unit's: its limits, ramps and start-up cost follow
    cost = np.round(d.cost * base.unit_array("cost"), 2)
    # the award: in each hour the share of the fixed load that Table I awards the base, within the tie
    tie = _rounded(d.tie * peak)
    award_share = np.asarray(base.grid.p_sch, float) / np.asarray(base.fixed_load.forecast, float)
    p_sch = np.clip(_rounded(award_share * loads), -tie[:, None], tie[:, None])
    # each renewable's share of the member's renewable capacity: wind's drawn, the others' the rest, in equal parts
    wind = np.array([r.name == "wind" for r in base.renewables], dtype=bool)
    share = np.where(wind, d.wind[:, None], 1.0 - d.wind[:, None])
    share = share / np.maximum(share.sum(axis=1, keepdims=True), 1e-12)
    r_cap = _rounded(d.renewable[:, None] * peak[:, None] * share)
    cases = []
    for k, name in enumerate(names):
        shape = list(LOAD_SHAPES)[d.shape[k]]
        kind = list(STORAGE_KINDS)[d.storage[k]] if base.storage is not None else "none"
        data = base.model_dump(exclude_none=True)
        data["case"] = {"name": f"{base.name}-{name}", "description": (
            f"{name}, drawn from {base.name} with seed {seed}: {shape} load ({loads[k].sum():.1f} MWh a day, peak "
            f"{peak[k]:.2f} MW), units {'+'.join(u.name for u, on in zip(base.units, d.units[k]) if on)} "
            f"({p_max[k].sum():.2f} MW), renewables {r_cap[k].sum():.2f} MW ({100 * d.wind[k]:.0f}% wind), "
            f"{'no' if kind == 'none' else kind} storage, tie {tie[k]:.2f} MW"),
            "provenance": {"drawn": "scenarios/diverse.py; docs/agent.md, \"Generated fleets\""}}
        data["fixed_load"] = {"forecast": loads[k].tolist(), "provenance": {"forecast": (
            f"{shape}: the {base.name} forecast rolled {d.roll[k]:+d} h, its contrast x{d.contrast[k]:.3f}, "
            f"times {d.size[k]:.4f}")}}
        data["units"] = [_unit(u, factor[k, g], cost[k, g]) for g, u in enumerate(base.units) if d.units[k, g]]
        data["renewables"] = [
            {"name": r.name, "capacity": r_cap[k, j],
             "forecast": np.minimum(_rounded(np.asarray(r.forecast) * r_cap[k, j] / r.capacity), r_cap[k, j]).tolist()}
            for j, r in enumerate(base.renewables) if r_cap[k, j] > 0]
        if kind == "none":
            data.pop("storage", None)
        else:
            data["storage"] = _sized(base.storage, d.size[k] * d.storage_size[k])
        data["loads"] = [_moved(load, d.size[k], d.roll[k]) for load in base.loads]
        data["grid"] = {**data["grid"], "p_m_max": tie[k], "p_sch": p_sch[k].tolist(), "provenance": {
            "p_m_max": f"drawn: {d.tie[k]:.3f} x peak fixed load",
            "p_sch": f"each hour's fixed load times the share Table I awards {base.name} in that hour"}}
        case = parse_case(data, f"drawn case {name}")
        problems = schedulable_problems(case)
        if problems:
            raise CaseError(f"drawn case {name}: {problems[0]}")
        cases.append(case)
    return cases


def _unit(unit, factor: float, cost: float) -> dict:
    """A unit of the base at ``factor`` times its size and at ``cost``; its times and initial state kept."""
    out = unit.model_dump(exclude_none=True)
    for field in ("p_min", "p_max", "ramp_up", "ramp_down", "startup_cost", "shutdown_cost", "p_initial"):
        if field in out:
            out[field] = float(_rounded(out[field] * factor))
    if unit.initial_on and "p_initial" in out:
        out["p_initial"] = min(max(out["p_initial"], out["p_min"]), out["p_max"])
    out["cost"] = float(cost)
    out["provenance"] = {"drawn": f"{unit.name} of the base at x{factor:.4f} its size, x{cost / unit.cost:.4f} its cost"}
    return out


def _sized(storage, factor: float) -> dict:
    """The base's storage at ``factor`` times its energy and power, its minimum times kept."""
    out = storage.model_dump()
    for field in ("c_max", "p_dch_min", "p_dch_max", "p_ch_min", "p_ch_max", "c_initial"):
        out[field] = float(_rounded(out[field] * factor))
    out["c_initial"] = min(out["c_initial"], out["c_max"])
    out["provenance"] = {"drawn": f"the base's storage at x{factor:.4f}"}
    return out


def _moved(load, size: float, roll: int) -> dict:
    """An adjustable load of the base at the member's size, its window moved with the load shape's roll but kept
    whole inside the day."""
    out = load.model_dump()
    for field in ("d_min", "d_max", "energy"):
        out[field] = float(_rounded(out[field] * size))
    out["energy"] = min(out["energy"], out["d_max"] * (load.beta - load.alpha + 1))
    alpha = int(np.clip(load.alpha + roll, 1, HOURS - (load.beta - load.alpha)))
    out.update(alpha=alpha, beta=alpha + load.beta - load.alpha, provenance={})
    return out


def schedulable_problems(case: Case) -> list[str]:
    """What keeps an agent from scheduling ``case`` without shedding load while connected, one line each (none: it
    can): in every hour its units and tie carry its fixed load and every adjustable load at its maximum; its award
    is within its tie; each adjustable load can run its minimum time at its minimum power within its energy; its
    storage can hold a whole minimum charge and a whole minimum discharge from where it starts."""
    problems = []
    demand = np.asarray(case.fixed_load.forecast) + case.load_array("d_max") @ case.load_windows
    supply = case.unit_array("p_max").sum() + case.grid.p_m_max
    short = np.flatnonzero(demand > supply + 1e-9)
    if short.size:
        t = short[0]
        problems.append(f"hour {t + 1}: demand {demand[t]:.3f} MW exceeds units and tie together ({supply:.3f} MW)")
    if np.abs(case.grid.p_sch).max() > case.grid.p_m_max + 1e-9:
        problems.append(f"award {np.abs(case.grid.p_sch).max():.3f} MW exceeds the tie ({case.grid.p_m_max:.3f} MW)")
    for load in case.loads:
        if load.d_min * load.min_up > load.energy + 1e-9:
            problems.append(f"load {load.name}: its minimum run ({load.min_up} h at {load.d_min} MW) exceeds its "
                            f"energy ({load.energy} MWh)")
    s = case.storage
    if s is not None and (s.min_charge * s.p_ch_min > s.c_max - s.c_initial + 1e-9
                          or s.min_discharge * s.p_dch_min > s.c_initial + 1e-9):
        problems.append(f"storage {s.name}: a minimum charge or discharge does not fit its energy from where it starts")
    return problems


def generate_fleet(n: int, seed: int = 0, base: str = "paper") -> list[FleetMember]:
    """n members mg1..mgN drawn from ``base`` (docs/agent.md, "Generated fleets"), each member's case in memory
    (``FleetMember.drawn``) until a fleet file holds it (``scenarios.fleet.write_fleet``). Member i draws from its own
    stream ``[seed, i]``, so a larger fleet extends a smaller one."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_MEMBERS:
        raise ValueError(f"a fleet has 1..{MAX_MEMBERS} members, not {n!r}")
    check_seed(seed)
    return list(_generated(n, seed, base))


@functools.lru_cache(maxsize=4)  # each role asks for its fleet several times; drawing 200 cases takes a second
def _generated(n: int, seed: int, base: str) -> tuple[FleetMember, ...]:
    case = load_case(base)
    width = DRAWS_PER_MEMBER + 3 * len(case.units)
    streams = [np.random.default_rng([seed, i]) for i in range(1, n + 1)]
    uniforms = np.array([rng.random(width) for rng in streams])
    day_seeds = [int(rng.integers(2**31)) for rng in streams]
    names = [f"mg{i}" for i in range(1, n + 1)]
    cases = drawn_cases(case, draw(uniforms, len(case.units)), names, seed)
    return tuple(FleetMember(name, base, seed=day_seed, drawn=c) for name, day_seed, c in zip(names, day_seeds, cases))


def summary(case: Case) -> dict:
    """What sets one microgrid apart from another, read from its case: fixed-load energy (MWh a day), peak and
    load factor, its units and their capacity, wind and solar capacity (MW), storage energy (MWh), its tie (MW)."""
    load = np.asarray(case.fixed_load.forecast, float)
    renewable = {kind: sum(r.capacity for r in case.renewables if (r.name == "wind") == (kind == "wind"))
                 for kind in ("wind", "solar")}
    return {"energy_mwh": float(load.sum()), "peak_mw": float(load.max()),
            "load_factor": float(load.mean() / load.max()) if load.max() > 0 else 0.0,
            "peak_hour": int(np.argmax(load)) + 1, "units": "+".join(u.name for u in case.units),
            "dispatchable_mw": float(case.unit_array("p_max").sum()), "wind_mw": float(renewable["wind"]),
            "solar_mw": float(renewable["solar"]), "storage_mwh": case.storage.c_max if case.storage else 0.0,
            "tie_mw": case.grid.p_m_max}
