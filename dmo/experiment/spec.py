"""An experiment: one file (TOML) that fixes everything a run depends on: its agents, market, days, seed, each
agent's solver settings, deadlines and faults (docs/experiments.md).

Every key has a default, so an empty file (or none) is the default day of ``dmosim run``, and a flag given on the
command line overrides the file. The resolved experiment, defaults included, is written into the run directory
and into the recording, so any run can be repeated (``dmosim run --from RECORDING``).
"""

from __future__ import annotations

import datetime as dt
import json
import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from microgrid_agent.solvers.routes import METHODS
from scenarios.case import read_toml
from scenarios.horizon import HOURS

from ..market.choice import rule_name


class ExperimentError(ValueError):
    """An experiment file or setting that cannot be used; the message is one line naming the file and the key."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


PositiveInt = Annotated[int, Field(ge=1)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Seconds = Annotated[float, Field(gt=0, le=86_400, allow_inf_nan=False)]
Scales = Annotated[list[Annotated[float, Field(gt=0, allow_inf_nan=False)]], Field(max_length=366)]


class Agents(_Section):
    """Who takes part: ``count`` agents mg1..mgN drawn around the market's case, or the members of a fleet file."""

    count: PositiveInt = 3
    fleet: str | None = None  # a fleet file, relative to the experiment file


class Market(_Section):
    """The DMO's terms: the case giving the ISO price, penalty and Table I awards; how awards are made; limits."""

    case: str = "paper"
    mode: Literal["bids", "fixed"] = "bids"
    penalty: NonNegative | None = None  # $/MWh above the award (None: the case's)
    credit: NonNegative = 0.0           # $/MWh below the award
    settlement: str | None = None       # the settlement rule, docs/settlement.md (None: paper at penalty and credit)

    @field_validator("settlement")
    @classmethod
    def _a_rule(cls, value: str | None) -> str | None:
        if value is not None:
            rule_name(value)  # a name only: parsing an experiment never imports a rule (the run that uses it loads it)
        return value
    import_limit: NonNegative | None = None  # MW (None: 8 x agents)
    export_limit: NonNegative | None = None  # MW (None: 5 x agents)
    island_hours: Annotated[int, Field(ge=0, le=HOURS)] = 1
    subperiods: Annotated[int, Field(ge=1, le=60)] = 6


class ScheduleSettings(_Section):
    """How each agent solves its stochastic schedule."""

    scenarios: PositiveInt = 5
    gap: Annotated[float, Field(ge=0, lt=1)] = 0.01
    time_limit: Seconds = 600.0
    method: Literal[METHODS] = "auto"  # type: ignore[valid-type]
    workers: PositiveInt = 1


class Profiles(_Section):
    """Each day's forecasts scaled, a pattern repeated over the days (e.g. a week with a lighter weekend)."""

    load_scale: Scales = []
    renewable_scale: Scales = []


class Deadlines(_Section):
    """Seconds each phase may take: registration, bids, schedules, each hour's meter reports."""

    registration: Seconds = 60.0
    bid: Seconds = 600.0
    schedule: Seconds = 1800.0
    hour: Seconds = 300.0


class Experiment(_Section):
    """A whole run. ``market_day`` None means today (resolved when the run starts)."""

    name: str = "run"
    seed: int = 0
    days: Annotated[int, Field(ge=1, le=3660)] = 1
    market_day: str | None = None
    agents: Agents = Agents()
    market: Market = Market()
    schedule: ScheduleSettings = ScheduleSettings()
    profiles: Profiles = Profiles()
    deadlines: Deadlines = Deadlines()
    faults: list[str] = []

    @field_validator("market_day")
    @classmethod
    def _a_date(cls, value):
        if value is not None:
            try:
                dt.date.fromisoformat(value)
            except ValueError:
                raise ValueError(f"{value!r} is not a date YYYY-MM-DD") from None
        return value


# The settings a command-line flag can override: dotted key -> flag dest of ``dmosim run``.
FLAGS = {
    "seed": "seed", "days": "days", "market_day": "market_day", "agents.count": "agents", "agents.fleet": "fleet",
    "market.case": "case", "market.mode": "market", "market.penalty": "penalty", "market.credit": "credit",
    "market.settlement": "settlement",
    "market.import_limit": "import_limit", "market.export_limit": "export_limit",
    "market.island_hours": "island_hours", "market.subperiods": "subperiods",
    "schedule.scenarios": "scenarios", "schedule.gap": "gap", "schedule.time_limit": "time_limit",
    "schedule.method": "method", "schedule.workers": "workers",
    "profiles.load_scale": "load_scale", "profiles.renewable_scale": "renewable_scale",
    "deadlines.registration": "registration_timeout", "deadlines.bid": "bid_timeout",
    "deadlines.schedule": "schedule_timeout", "deadlines.hour": "hour_timeout",
}


def parse_experiment(data: dict, source: str = "<experiment>") -> Experiment:
    """Validate an experiment given as a dict; any problem raises ExperimentError naming the source and the key."""
    try:
        return Experiment.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "experiment"
        what = "unknown key" if err["type"] == "extra_forbidden" else err["msg"].removeprefix("Value error, ")
        raise ExperimentError(f"{source}: {where}: {what}") from None


def load_experiment(path: str | Path) -> Experiment:
    """Read and validate an experiment file; a fleet it names is taken relative to the file."""
    path = Path(path)
    data = read_toml(path, "experiment", ExperimentError)
    fleet = data.get("agents", {}).get("fleet") if isinstance(data.get("agents"), dict) else None
    if isinstance(fleet, str) and not Path(fleet).is_absolute():
        data["agents"]["fleet"] = str(path.parent / fleet)
    return parse_experiment(data, str(path))


def with_settings(experiment: Experiment, settings: dict[str, object], source: str) -> Experiment:
    """The experiment with dotted keys replaced (``market.penalty``, ``seed``...), validated again."""
    data = experiment.model_dump()
    for key, value in settings.items():
        *path, last = key.split(".")
        node = data
        for part in path:
            if not isinstance(node.get(part), dict):
                raise ExperimentError(f"{source}: {key}: unknown key")
            node = node[part]
        if last not in node:
            raise ExperimentError(f"{source}: {key}: unknown key")
        node[last] = value
    return parse_experiment(data, source)


def to_toml(experiment: Experiment) -> str:
    """The experiment as a TOML file that ``load_experiment`` reads back to the same experiment."""
    data = experiment.model_dump()
    lines = [f"# dmosim experiment: {experiment.name}"]
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    for key, value in data.items():
        if not isinstance(value, dict) and value is not None:
            lines.append(f"{key} = {_value(value)}")
    for name, table in tables.items():
        lines += ["", f"[{name}]"]
        lines += [f"{key} = {_value(value)}" for key, value in table.items() if value is not None]
    return "\n".join(lines) + "\n"


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, str)):
        return json.dumps(value)
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} to TOML")
