"""An experiment: one file (TOML) that fixes everything a run depends on: its agents, market, days, seed, each
agent's solver settings, deadlines and faults (docs/experiments.md).

Every key has a default, so an empty file (or none) is the default day of ``dmosim run``, and a flag given on the
command line overrides the file. The resolved experiment, defaults included, is written into the run directory
and into the recording, so any run can be repeated (``dmosim run --from RECORDING``).
"""

from __future__ import annotations

import datetime as dt
import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from dmo.market.choice import ChosenRule, choose, paper_rule, rule_name
from dmo.market.clearing import CLEARING_METHODS, MAX_BLOCKS, IsoCurve
from dmo.market.rules import BUILT_IN, MAX_MW, MAX_RATE, market_parameters
from dmo.operator.config import CLOCKS, LOGICAL
from messages.schemas import MAX_AGENTS, MAX_DAYS, MAX_SUBPERIODS, PRICE_CAP
from messages.transport.credentials import MAX_HOSTS
from microgrid_agent.agent.strategies import DEFAULT_STRATEGY, StrategyError, strategy_name
from microgrid_agent.solvers.routes import METHODS, check_available
from scenarios.case import read_toml
from scenarios.days import MAX_SEED, market_days
from scenarios.fleet import MAX_SCALE, MAX_STRATEGY
from scenarios.generation import MAX_SCENARIOS
from scenarios.horizon import HOURS
from scenarios.network import MAX_NAME_LENGTH
from scenarios.tomltext import toml_text

# Bounds of the settings defined here (the others are where theirs are: docs/experiments.md, "Bounds").
MAX_WORKERS = 64           # Benders processes per agent: each holds its scenarios' LPs; more than a host's cores
                           # only adds memory
MAX_SECONDS = 86_400.0     # a deadline or time limit: a day of wall-clock time, 170 x the longest solve measured
MAX_PROFILE_DAYS = 366     # a profile pattern (load_scale...) is repeated over the days: a year's at most
MAX_FAULTS = 100           # faults of one run; each process checks every message fault on every publication
MAX_PATH = 4096            # a file's path (a case, a fleet), as Linux's PATH_MAX
MAX_RULE = 500             # a settlement rule as named: what an award's settlement_rule may carry
MAX_FAULT_SPEC = 200       # one fault as written
MAX_NAME = 100             # an experiment's name: part of a sweep's directory name
MAX_VOLTAGE_MARGIN = 0.1   # p.u. kept inside a bus's voltage limits: a tenth of nominal, twice ANSI's whole band
# How the agents run (dmosim/launch/local.py): each a Python process of its own, or forked from one process that has
# imported their code, sharing its memory; or, with the DMO and the recorder, in the launcher's own process, with no
# network (dmosim/launch/inprocess.py). The market's results are the same every way.
IN_PROCESS = "in-process"
HOSTINGS = ("auto", "process", "fork", IN_PROCESS)


class ExperimentError(ValueError):
    """An experiment file or setting that cannot be used; the message is one line naming the file and the key."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


Rate = Annotated[float, Field(ge=0, le=MAX_RATE, allow_inf_nan=False)]
Megawatts = Annotated[float, Field(ge=0, le=MAX_MW, allow_inf_nan=False)]
Seconds = Annotated[float, Field(gt=0, le=MAX_SECONDS, allow_inf_nan=False)]
Scales = Annotated[list[Annotated[float, Field(gt=0, le=MAX_SCALE, allow_inf_nan=False)]],
                   Field(max_length=MAX_PROFILE_DAYS)]
PathText = Annotated[str, Field(min_length=1, max_length=MAX_PATH)]
# An ISO curve's side: blocks [MW, $/MWh away from the ISO's price]; IsoCurve checks their order
Blocks = Annotated[list[Annotated[list[Annotated[float, Field(ge=0, le=MAX_MW, allow_inf_nan=False)]],
                                  Field(min_length=2, max_length=2)]], Field(max_length=MAX_BLOCKS)]


class Agents(_Section):
    """Who takes part: ``count`` agents mg1..mgN drawn around the paper's case, or ``generate`` agents mg1..mgN drawn
    diverse from the experiment's seed (scenarios/diverse.py; a run writes them into its run directory as a fleet
    file), or the members of a fleet file; ``strategy`` how each bids (docs/strategies.md), unless its fleet entry
    names its own; ``hosting`` how ``dmosim run`` starts their processes (``HOSTINGS``; ``auto`` chooses by the
    fleet's size, dmosim/launch/roles.py), and with ``fork`` how many agents each runs (``per_process``; None: one,
    or with ``auto`` as it chooses); ``routers`` the Zenoh routers it starts for them, each standing for one
    host's (launch/mesh.py), or none: the DMO is their router."""

    count: Annotated[int, Field(ge=1, le=MAX_AGENTS)] = 3
    fleet: PathText | None = None  # a fleet file, relative to the experiment file
    generate: Annotated[int, Field(ge=1, le=MAX_AGENTS)] | None = None
    strategy: Annotated[str, Field(min_length=1, max_length=MAX_STRATEGY)] = DEFAULT_STRATEGY
    hosting: Literal[HOSTINGS] = "auto"  # type: ignore[valid-type]
    per_process: Annotated[int, Field(ge=1, le=MAX_AGENTS)] | None = None  # agents a forked process runs, a thread each
    routers: Annotated[int, Field(ge=0, le=MAX_HOSTS)] = 0  # dmosim routers started, one per host (0: the DMO is it)

    @field_validator("strategy")
    @classmethod
    def _a_strategy(cls, value: str) -> str:
        try:
            strategy_name(value)  # a name only: parsing an experiment never imports a strategy (its agents do)
        except StrategyError as err:
            raise ValueError(str(err)) from None
        return value

    @model_validator(mode="after")
    def _one_way(self):
        counted = self.count != Agents.model_fields["count"].default
        if self.fleet is not None and counted:
            raise ValueError("count and fleet exclude each other: a fleet file names its agents")
        if self.generate is not None and (counted or self.fleet is not None):
            other = "count" if counted else "fleet"
            raise ValueError(f"{other} and generate exclude each other: generate draws that many agents of its own")
        if self.per_process is not None and self.per_process > 1 and self.hosting != "fork":
            raise ValueError(f"per_process = {self.per_process} needs hosting = \"fork\": agents share a process "
                             "forked from their host")
        return self


class Market(_Section):
    """The DMO's terms: the case giving the ISO price, penalty and Table I awards; how awards are made; limits."""

    case: PathText = "paper"
    mode: Literal["bids", "fixed"] = "bids"
    penalty: Rate | None = None  # $/MWh above the award (None: the case's)
    credit: Rate = 0.0           # $/MWh below the award
    # the settlement rule, docs/settlement.md (None: paper at penalty and credit)
    settlement: Annotated[str, Field(max_length=MAX_RULE)] | None = None

    @field_validator("settlement")
    @classmethod
    def _a_rule(cls, value: str | None) -> str | None:
        if value is not None:
            rule_name(value)  # a name only: parsing an experiment never imports a rule (the run that uses it loads it)
        return value
    import_limit: Megawatts | None = None  # MW (None: 8 x agents)
    export_limit: Megawatts | None = None  # MW (None: 5 x agents)
    # the ISO's curve (docs/market.md, "The ISO's curve"): [MW, $/MWh over its price] it sells the DMO in order,
    # [MW, $/MWh under its price] it buys; none: all at its price, within the limits
    import_curve: Blocks = []
    export_curve: Blocks = []
    island_hours: Annotated[int, Field(ge=0, le=HOURS)] = 1
    subperiods: Annotated[int, Field(ge=1, le=MAX_SUBPERIODS)] = 6

    @model_validator(mode="after")
    def _rule_and_terms(self):
        """A built-in rule and the market's penalty and credit agree (``rules.market_parameters``); a rule of one's
        own takes them as the term its agents schedule against."""
        chosen = built_in_rule(self.settlement) if self.settlement is not None else None
        if chosen is not None:  # the case's penalty only fills in a rate; a disagreement does not depend on it
            market_parameters(chosen.built_in, chosen.params, self.penalty, self.credit, case_penalty=0.0)
        return self

    @model_validator(mode="after")
    def _a_curve(self):
        if (self.import_curve or self.export_curve) and self.mode == "fixed":
            raise ValueError("import_curve and export_curve price the clearing; mode \"fixed\" clears nothing")
        self.iso_curve  # raises ValueError unless each side's blocks are in order
        return self

    @property
    def iso_curve(self) -> IsoCurve:
        """The ISO's curve the market clears against (``dmo.market.clearing.IsoCurve``)."""
        return IsoCurve(tuple(map(tuple, self.import_curve)), tuple(map(tuple, self.export_curve)))


class ScheduleSettings(_Section):
    """How each agent solves its stochastic schedule."""

    scenarios: Annotated[int, Field(ge=1, le=MAX_SCENARIOS)] = 5
    gap: Annotated[float, Field(ge=0, lt=1)] = 0.01
    # None: no limit of seconds, the gap alone ends a solve, so its schedule is the same on any machine at any load
    time_limit: Seconds | None = None
    method: Literal[METHODS] = "auto"  # type: ignore[valid-type]
    workers: Annotated[int, Field(ge=1, le=MAX_WORKERS)] = 1

    @field_validator("method")
    @classmethod
    def _installed(cls, method: str) -> str:
        return check_available(method)


class Profiles(_Section):
    """Each day's forecasts scaled, a pattern repeated over the days (e.g. a week with a lighter weekend)."""

    load_scale: Scales = []
    renewable_scale: Scales = []


class Deadlines(_Section):
    """How a phase ends (``clock``), and the seconds each may take on the wall clock: registration, bids,
    schedules, each hour's meter reports. On the logical clock (the default) a phase ends when every live agent has
    answered, so a run is the same however busy the machine is; on the wall clock, at the latest at its deadline."""

    clock: Literal[CLOCKS] = LOGICAL  # type: ignore[valid-type]
    registration: Seconds = 60.0
    bid: Seconds = 600.0
    schedule: Seconds = 1800.0
    hour: Seconds = 300.0


class NetworkSettings(_Section):
    """The feeder the market clears on (docs/network.md): none (the default) is the copper plate. ``feeder`` is a
    built-in network or a network file (TOML or pandapower JSON, relative to the experiment file); ``buses`` places
    the agents, in the fleet's order, where a fleet file gives no bus (else they are spread over the feeder);
    ``clearing`` clears on the AC flow ("ac", the default) or on LinDistFlow alone; ``spill_price`` ($/MWh) is what
    spilling a MW of the feeder's fixed generation costs (docs/market.md)."""

    feeder: PathText | None = None
    load_scale: Annotated[float, Field(gt=0, le=MAX_SCALE, allow_inf_nan=False)] = 1.0
    voltage_margin: Annotated[float, Field(ge=0, le=MAX_VOLTAGE_MARGIN, allow_inf_nan=False)] = 0.0
    clearing: Literal[CLEARING_METHODS] = "ac"  # type: ignore[valid-type]
    spill_price: Annotated[float, Field(ge=0, le=PRICE_CAP, allow_inf_nan=False)] = 0.0
    buses: Annotated[list[Annotated[str, Field(min_length=1, max_length=MAX_NAME_LENGTH)]],
                     Field(max_length=MAX_AGENTS)] = []


class Experiment(_Section):
    """A whole run. ``market_day`` None means today (resolved when the run starts)."""

    name: str = "run"
    seed: Annotated[int, Field(ge=0, le=MAX_SEED)] = 0
    days: Annotated[int, Field(ge=1, le=MAX_DAYS)] = 1
    market_day: str | None = None
    agents: Agents = Agents()
    market: Market = Market()
    schedule: ScheduleSettings = ScheduleSettings()
    profiles: Profiles = Profiles()
    deadlines: Deadlines = Deadlines()
    network: NetworkSettings = NetworkSettings()
    faults: Annotated[list[Annotated[str, Field(max_length=MAX_FAULT_SPEC)]], Field(max_length=MAX_FAULTS)] = []

    @model_validator(mode="after")
    def _bids_on_a_feeder(self):
        if self.network.feeder is not None and self.market.mode == "fixed":
            raise ValueError("network.feeder: a feeder is cleared from bids; market.mode \"fixed\" publishes given "
                             "awards and clears nothing")
        return self

    @model_validator(mode="after")
    def _in_one_process(self):
        """A market in one process has no network and no processes to fault, and runs on the logical clock."""
        if self.agents.hosting != IN_PROCESS:
            return self
        if self.faults:
            raise ValueError(f"faults: hosting \"{IN_PROCESS}\" has no processes to kill and no network to lose "
                             "messages on; run the faults as processes")
        if self.agents.routers:
            raise ValueError(f"agents.routers: hosting \"{IN_PROCESS}\" has no network")
        if self.deadlines.clock != LOGICAL:
            raise ValueError(f"deadlines.clock: hosting \"{IN_PROCESS}\" runs on the logical clock only")
        return self

    @field_validator("name")
    @classmethod
    def _a_name(cls, value: str) -> str:
        if not 1 <= len(value) <= MAX_NAME or re.search(r"[/\\\x00-\x1f\x7f]", value):
            raise ValueError(f"a name is 1..{MAX_NAME} characters with no / or \\ and no control characters "
                             "(it names the sweep's directory)")
        return value

    @field_validator("market_day", mode="before")
    @classmethod
    def _a_toml_date(cls, value):
        """A TOML date (``market_day = 2026-07-01``, unquoted) is the same day as its string."""
        return value.isoformat() if type(value) is dt.date else value

    @field_validator("market_day")
    @classmethod
    def _a_date(cls, value, info: ValidationInfo):
        """A date YYYY-MM-DD (as the wire writes it) whose run of ``days`` ends by 9999-12-31."""
        if value is not None:
            try:
                if not re.fullmatch(r"[0-9]{4}-[0-9]{2}-[0-9]{2}", value):
                    raise ValueError
                dt.date.fromisoformat(value)
            except ValueError:
                raise ValueError(f"{value!r} is not a date YYYY-MM-DD") from None
            if "days" in info.data:
                market_days(value, info.data["days"])  # a ValueError says when the run would end
        return value


# The settings a command-line flag can override: dotted key -> flag dest of ``dmosim run``, ``dmo`` and ``agent``
# (dmosim/cli/settings.py).
FLAGS = {
    "seed": "seed", "days": "days", "market_day": "market_day", "agents.count": "agents", "agents.fleet": "fleet",
    "agents.generate": "generate",
    "agents.strategy": "strategy", "agents.hosting": "hosting", "agents.per_process": "per_process",
    "agents.routers": "routers",
    "market.case": "case", "market.mode": "market", "market.penalty": "penalty", "market.credit": "credit",
    "market.settlement": "settlement",
    "market.import_limit": "import_limit", "market.export_limit": "export_limit",
    "market.island_hours": "island_hours", "market.subperiods": "subperiods",
    "schedule.scenarios": "scenarios", "schedule.gap": "gap", "schedule.time_limit": "time_limit",
    "schedule.method": "method", "schedule.workers": "workers",
    "profiles.load_scale": "load_scale", "profiles.renewable_scale": "renewable_scale",
    "deadlines.clock": "clock", "deadlines.registration": "registration_timeout", "deadlines.bid": "bid_timeout",
    "deadlines.schedule": "schedule_timeout", "deadlines.hour": "hour_timeout",
    "network.feeder": "feeder", "network.load_scale": "network_load_scale",
    "network.voltage_margin": "voltage_margin", "network.clearing": "clearing", "network.spill_price": "spill_price",
}


def built_in_rule(spec: str) -> ChosenRule | None:
    """The built-in rule ``spec`` names, ``NAME`` or ``NAME:key=value,...`` (ValueError if its parameters are
    wrong), or None for a rule of one's own, which is not loaded here."""
    name, _, params = spec.strip().partition(":")
    if name not in BUILT_IN or ":" in params or (params and "=" not in params):
        return None
    return choose(spec)


def settled_by(market: Market, case_penalty: float) -> str:
    """The rule the market's days are settled by, as the DMO names it (its case's penalty ``case_penalty``): a
    built-in with every parameter, a rule of one's own as named."""
    if market.settlement is None:
        return paper_rule(case_penalty if market.penalty is None else market.penalty, market.credit).label
    chosen = built_in_rule(market.settlement)
    return market.settlement if chosen is None else with_market_terms(chosen, market, case_penalty).label


def with_market_terms(chosen: ChosenRule, market: Market, case_penalty: float) -> ChosenRule:
    """A built-in rule with the parameters it settles by in ``market`` (``rules.market_parameters``: ``paper`` takes
    the rates it is not given from the market's penalty, else its case's ``case_penalty``, and credit; ValueError
    where they disagree); a rule of one's own as it is."""
    if chosen.built_in is None:
        return chosen
    params = market_parameters(chosen.built_in, chosen.params, market.penalty, market.credit, case_penalty)
    return ChosenRule(chosen.name, chosen.rule, params)


def parse_experiment(data: dict, source: str = "<experiment>") -> Experiment:
    """Validate an experiment given as a dict; any problem raises ExperimentError naming the source and the key."""
    try:
        return Experiment.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(p if re.fullmatch(r"[\w-]+", str(p), re.ASCII) else repr(p) for p in map(str, err["loc"]))
        what = "unknown key" if err["type"] == "extra_forbidden" else err["msg"].removeprefix("Value error, ")
        message = f"{source}: {where or 'experiment'}: {what}"
        raise ExperimentError(message.replace("\n", "\\n")) from None  # one line, whatever a key or rule says


def load_experiment(path: str | Path) -> Experiment:
    """Read and validate an experiment file; a fleet it names is taken relative to the file."""
    path = Path(path)
    data = read_toml(path, "experiment", ExperimentError)
    for section, key in (("agents", "fleet"), ("network", "feeder")):
        value = data.get(section, {}).get(key) if isinstance(data.get(section), dict) else None
        if isinstance(value, str) and not Path(value).is_absolute() and (key != "feeder" or Path(value).suffix):
            data[section][key] = str(path.parent / value)  # a file; a built-in feeder's name has no suffix
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
    return toml_text(experiment.model_dump(), f"dmosim experiment: {experiment.name}")
