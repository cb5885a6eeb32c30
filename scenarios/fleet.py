"""Fleets of heterogeneous microgrids: cases derived from a base case by size and time shift, seeded or from a file,
and fleet files written back (with a case file per member whose case was drawn: scenarios/diverse.py).

A fleet file (TOML) lists its agents::

    [[agents]]
    id = "mg1"            # agent id: ^[A-Za-z][A-Za-z0-9_-]{0,31}$, not "dmo" or "recorder"
    case = "paper"        # built-in case name, or a case file path relative to the fleet file
    scale = 1.0           # in (0, 10]: every power and energy quantity is multiplied by it (default 1)
    shift_hours = 0       # -23..23: load, renewable and award profiles rolled by this many hours (default 0)
    seed = 1              # 0..2**32-1: the agent's realised-day seed (default: its position in the file, 1-based)
    strategy = "naive"    # its bidding strategy, docs/strategies.md (default: the experiment's agents.strategy)
    bus = "18"            # its bus on the market's feeder, docs/network.md (default: the experiment's placement)

A file lists at most ``MAX_MEMBERS`` agents.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenarios.case import Case, CaseError, builtin_cases, case_toml, load_case, parse_case, read_toml
from scenarios.days import check_seed
from scenarios.names import check_agent_id
from scenarios.network import MAX_NAME_LENGTH
from scenarios.tomltext import toml_text

SCALE_RANGE = (0.6, 1.4)
SHIFTS = (-2, -1, 0, 1, 2)
# The protocol's day summary lists at most 1,024 agents (messages.schemas.MAX_AGENTS, which this package, below
# messages, cannot import; tests/scenarios/test_fleet.py checks the two agree).
MAX_MEMBERS = 1024
# The largest multiplier of a microgrid's size, and of its profiles: ten times the paper's microgrid ties to the
# grid at 160 MW, more than any microgrid; above it a scaled day is all curtailment or all spill.
MAX_SCALE = 10.0
MAX_SHIFT_HOURS = 23  # a shift of 24 h or more is a shift of less: the day is rolled round
_FIELDS = ("id", "case", "scale", "shift_hours", "seed", "strategy", "bus")
_DEFAULTS = {"scale": 1.0, "shift_hours": 0}  # what a written entry leaves out (its seed is always written)
CASES_DIR = "cases"  # beside a written fleet file: the case file of each member whose case was drawn
MAX_STRATEGY = 500  # a strategy as named: what a registration's strategy may carry

# Quantities in MW or MWh, by part of the case; costs, times, windows and prices are kept.
_SCALED = {
    "units": ("p_min", "p_max", "ramp_up", "ramp_down", "p_initial"),
    "renewables": ("capacity", "forecast"),
    "storage": ("c_max", "p_dch_min", "p_dch_max", "p_ch_min", "p_ch_max", "c_initial"),
    "loads": ("d_min", "d_max", "energy"),
    "fixed_load": ("forecast",),
    "grid": ("p_m_max", "p_sch"),
}
_SHIFTED = {"renewables": ("forecast",), "fixed_load": ("forecast",), "grid": ("p_sch",)}


class FleetError(ValueError):
    """A fleet file that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class FleetMember:
    """One agent of a fleet: its id, its base case (built-in name or path), size, time shift, realised-day seed and
    bidding strategy as named (None: the experiment's; the name is checked where strategies are known,
    ``microgrid_agent.agent.strategies.strategy_name``), and its bus on the market's feeder (None: the
    experiment's placement; checked against the feeder where the run knows it). ``drawn`` is the member's own case
    when it was drawn in memory (scenarios/diverse.py; ``case`` then names the base it was drawn from) and no file
    holds it yet: ``write_fleet`` writes it to one."""

    id: str
    case: str
    scale: float = 1.0
    shift_hours: int = 0
    seed: int = 0
    strategy: str | None = None
    bus: str | None = None
    drawn: Case | None = field(default=None, hash=False, repr=False)


def _transform(data: dict, fields: dict[str, tuple[str, ...]], f) -> None:
    """Apply f to the named fields of each part of a dumped case, in place (parts may be lists or absent)."""
    for part, names in fields.items():
        items = data.get(part)
        for item in items if isinstance(items, list) else [items] if items else []:
            for name in names:
                if item.get(name) is not None:  # optional quantities (p_initial) stay unset
                    item[name] = f(item[name])


def derive_case(base: Case, scale: float, shift_hours: int, name: str) -> Case:
    """``base`` with every power and energy quantity times ``scale`` and the fixed load, renewable forecasts and
    award rolled ``shift_hours`` later (np.roll: the day stays 24 h). Costs, times, load windows, uncertainty
    bounds and the ISO price are kept. Scale 1 and shift 0 under the base's name give the base itself."""
    if not is_scale(scale):
        raise CaseError(f"derived case {name}: scale must be a number in (0, {MAX_SCALE:g}], got {scale!r}")
    if isinstance(shift_hours, bool) or not isinstance(shift_hours, (int, np.integer)):
        raise CaseError(f"derived case {name}: shift_hours must be an integer, got {shift_hours!r}")
    identity = scale == 1 and shift_hours == 0
    data = base.model_dump()
    if not identity:
        _transform(data, _SCALED, lambda x: (np.asarray(x, float) * scale).tolist() if isinstance(x, list) else x * scale)
        _transform(data, _SHIFTED, lambda x: np.roll(np.asarray(x, float), int(shift_hours)).tolist())
        data["case"]["provenance"] = {**data["case"]["provenance"],
                                      "derived": f"{base.name} scaled x{scale:g}, profiles shifted {int(shift_hours):+d} h"}
    data["case"]["name"] = name
    return parse_case(data, f"derived case {name}")


def is_scale(scale: object) -> bool:
    """Whether ``scale`` is a size or profile multiplier: a number in (0, MAX_SCALE]."""
    return (not isinstance(scale, bool) and isinstance(scale, (int, float)) and math.isfinite(scale)
            and 0 < scale <= MAX_SCALE)


def member_case(member: FleetMember) -> Case:
    """The member's case: its base case (the one drawn for it, else ``case``) derived by its scale and shift (the
    base itself when 1 and 0)."""
    base = member.drawn if member.drawn is not None else load_case(member.case)
    if member.scale == 1 and member.shift_hours == 0:
        return base
    return derive_case(base, member.scale, member.shift_hours, f"{base.name}-{member.id}")


def make_fleet(n: int, seed: int = 0, base: str = "paper") -> list[FleetMember]:
    """n members mg1..mgN of ``base``: mg1 the base as is, the others scaled by U(0.6, 1.4) and shifted by
    -2..2 hours. Member i draws from its own stream of ``seed``, so a larger fleet extends a smaller one."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_MEMBERS:
        raise ValueError(f"a fleet has 1..{MAX_MEMBERS} members, not {n!r}")
    check_seed(seed)
    members = []
    for i in range(1, n + 1):
        rng = np.random.default_rng([seed, i])
        scale, shift, day_seed = rng.uniform(*SCALE_RANGE), int(rng.choice(SHIFTS)), int(rng.integers(2**31))
        if i == 1:
            scale, shift = 1.0, 0
        members.append(FleetMember(f"mg{i}", base, round(float(scale), 4), shift, day_seed))
    return members


def write_fleet(members: list[FleetMember], path: str | Path, comment: str = "") -> Path:
    """Write ``members`` as the fleet file ``path`` that ``load_fleet`` reads back to the same cases, seeds, strategies
    and buses: a member with a drawn case gets the case file ``cases/<id>.toml`` beside it, the others name their
    case as they do. Returns ``path``; an existing file is replaced (the caller decides whether it may be)."""
    path = Path(path)
    entries = []
    for m in members:
        case = m.case
        if m.drawn is not None:
            case = f"{CASES_DIR}/{m.id}.toml"
            (path.parent / CASES_DIR).mkdir(parents=True, exist_ok=True)
            (path.parent / case).write_text(case_toml(m.drawn, f"{m.id} of the fleet {path.name} (dmosim)"))
        entry = {"id": m.id, "case": case, "scale": m.scale, "shift_hours": m.shift_hours, "seed": m.seed,
                 "strategy": m.strategy, "bus": m.bus}
        entries.append({k: v for k, v in entry.items() if v != _DEFAULTS.get(k)})
    path.write_text(toml_text({"agents": entries}, comment))
    return path


def _fail(path: Path, where: str, message: str):
    raise FleetError(f"{path}: {where}: {message}")


def _member(path: Path, index: int, entry, seen: set[str]) -> FleetMember:
    where = f"agents[{index}]"
    if not isinstance(entry, dict):
        _fail(path, where, "must be a table ([[agents]])")
    unknown = sorted(set(entry) - set(_FIELDS))
    if unknown:
        _fail(path, f"{where}.{unknown[0]}", f"unknown field (fields: {', '.join(_FIELDS)})")
    if "id" not in entry:
        _fail(path, f"{where}.id", "missing field")
    agent = entry["id"]
    try:
        check_agent_id(agent)
    except ValueError as exc:
        _fail(path, f"{where}.id", str(exc))
    if agent in seen:
        _fail(path, f"{where}.id", f"duplicate agent id {agent!r}")
    seen.add(agent)
    where = f"agents[{agent}]"
    scale = entry.get("scale", 1.0)
    if not is_scale(scale):
        _fail(path, f"{where}.scale", f"must be a number in (0, {MAX_SCALE:g}], got {scale!r}")
    shift = entry.get("shift_hours", 0)
    if isinstance(shift, bool) or not isinstance(shift, int) or not -MAX_SHIFT_HOURS <= shift <= MAX_SHIFT_HOURS:
        _fail(path, f"{where}.shift_hours",
              f"must be an integer in -{MAX_SHIFT_HOURS}..{MAX_SHIFT_HOURS}, got {shift!r}")
    seed = entry.get("seed", index + 1)
    try:
        check_seed(seed)
    except ValueError as exc:
        _fail(path, f"{where}.seed", str(exc))
    case = entry.get("case", "paper")
    if not isinstance(case, str) or not case:
        _fail(path, f"{where}.case", f"must be a case name or path, got {case!r}")
    if case not in builtin_cases():
        resolved = path.parent / case
        if not resolved.is_file():
            _fail(path, f"{where}.case", f"unknown case {case!r}: not a built-in case "
                                         f"({', '.join(builtin_cases())}) nor a file at {resolved}")
        case = str(resolved)
    strategy = entry.get("strategy")
    if strategy is not None and (not isinstance(strategy, str) or not 1 <= len(strategy.strip()) <= MAX_STRATEGY):
        _fail(path, f"{where}.strategy", f"must be a strategy's name of 1..{MAX_STRATEGY} characters, got {strategy!r}")
    bus = entry.get("bus")
    if bus is not None and (isinstance(bus, bool) or not isinstance(bus, (str, int))
                            or not 1 <= len(str(bus)) <= MAX_NAME_LENGTH):
        _fail(path, f"{where}.bus", f"must be a bus's name (a string or an integer), got {bus!r}")
    member = FleetMember(agent, case, float(scale), shift, seed, strategy, None if bus is None else str(bus))
    try:
        member_case(member)
    except CaseError as exc:
        _fail(path, f"{where}.case", str(exc))
    return member


def load_fleet(path: str | Path) -> list[FleetMember]:
    """Read and validate a fleet file; any problem raises FleetError with one line naming the file and the field.
    Each member's case is loaded and derived once here, so a bad case or scale fails now, not mid-run."""
    path = Path(path)
    data = read_toml(path, "fleet", FleetError)
    extra = sorted(set(data) - {"agents"})
    if extra:
        _fail(path, extra[0], "unknown table or key (a fleet file holds [[agents]] only)")
    agents = data.get("agents")
    if not isinstance(agents, list) or not agents:
        _fail(path, "agents", "missing: list at least one agent as [[agents]]")
    if len(agents) > MAX_MEMBERS:
        _fail(path, "agents", f"{len(agents)} agents; a fleet has at most {MAX_MEMBERS}")
    seen: set[str] = set()
    return [_member(path, i, entry, seen) for i, entry in enumerate(agents)]
