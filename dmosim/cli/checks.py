"""What ``dmosim run`` (``--check`` or not) and ``dmosim sweep`` check of an experiment beyond its own fields, before
anything starts: its fleet, its cases and its faults, each refused in one line (``ExperimentError``).
"""

from __future__ import annotations

from dmo.market.choice import choose
from messages.schemas import PRICE_CAP, PRICE_FLOOR
from messages.transport.faults import FaultSpecError
from microgrid_agent.agent.strategies import StrategyError, choose_strategy, strategy_name
from scenarios.case import CaseError, load_case
from scenarios.fleet import FleetError, FleetMember, member_case

from ..experiment.spec import Experiment, ExperimentError
from ..launch.faults import Fault, parse_fault
from ..launch.roles import fleet_of, network_of, placement_of, strategy_of


class Checked:
    """The fleets and cases already checked, so that a sweep of many variants reads each file once."""

    def __init__(self):
        self.fleets: dict[tuple, list[FleetMember]] = {}
        self.cases: set[str] = set()
        self.rules: set[str] = set()
        self.strategies: set[str] = set()

    def fleet(self, experiment: Experiment) -> list[FleetMember]:
        a = experiment.agents
        key = (a.fleet,) if a.fleet else (a.count, a.generate, experiment.seed)
        if key not in self.fleets:
            try:
                self.fleets[key] = fleet_of(experiment)
            except FleetError as exc:
                raise ExperimentError(str(exc)) from None
        return self.fleets[key]

    def case(self, name: str) -> None:
        if name not in self.cases:
            try:
                load_case(name)
            except CaseError as exc:
                raise ExperimentError(str(exc)) from None
            self.cases.add(name)

    def rule(self, spec: str | None) -> None:
        """The settlement rule an experiment the user runs names, loaded and tried on a trial day (it is theirs to
        run: ``choose``)."""
        if spec is not None and spec not in self.rules:
            try:
                choose(spec)
            except ValueError as exc:
                raise ExperimentError(f"market.settlement: {exc}") from None
            self.rules.add(spec)


    def strategy(self, spec: str, member: FleetMember, where: str) -> None:
        """A strategy an agent bids with, named by the user (``where`` says where): made, and one of their own tried
        on a trial call for ``member``'s case (``choose_strategy``)."""
        if spec not in self.strategies:
            try:
                choose_strategy(spec, member_case(member))
            except StrategyError as exc:
                raise ExperimentError(f"{where}: {exc}") from None
            self.strategies.add(spec)


def strategy_source(experiment: Experiment, member: FleetMember) -> str:
    """Where the strategy ``member`` bids with is named: its fleet entry, or the experiment's agents.strategy."""
    return f"{experiment.agents.fleet}: agents[{member.id}].strategy" if member.strategy else "agents.strategy"


def check_inputs(experiment: Experiment, checked: Checked | None = None) -> list[FleetMember]:
    """The experiment's fleet, once its cases load and its faults name its agents and days; else ExperimentError."""
    checked = checked or Checked()
    fleet = checked.fleet(experiment)
    for name in sorted({experiment.market.case, *(m.case for m in fleet)}):
        checked.case(name)
    for member in fleet:
        try:
            strategy_name(strategy_of(experiment, member))  # a name only: loading it is the caller's, if trusted
        except StrategyError as exc:
            raise ExperimentError(f"{strategy_source(experiment, member)}: {exc}") from None
    try:
        faults = [f for f in map(parse_fault, experiment.faults) if isinstance(f, Fault)]
    except (FaultSpecError, ValueError) as exc:  # ValueError: a digit int() cannot read, e.g. "²"
        raise ExperimentError(f"--fault: {exc}") from None
    unknown = sorted({f.agent for f in faults} - {m.id for m in fleet} - {"dmo", "recorder"})
    if any(f.agent == "dmo" and f.kind != "restart" for f in faults):
        raise ExperimentError("--fault: the DMO can only be restarted (restart:dmo:HOUR), not killed")
    if any(f.agent == "recorder" and f.kind != "kill" for f in faults):
        raise ExperimentError("--fault: the recorder can only be killed (kill:recorder:HOUR), not restarted")
    if unknown:
        raise ExperimentError(f"--fault names unknown agent {unknown[0]} (agents: {agent_list(fleet)})")
    late = [f for f in faults if f.day > experiment.days]
    if late:
        raise ExperimentError(f"--fault {late[0]}: day {late[0].day} is past the run's {experiment.days} day(s)")
    placement_of(experiment, network_of(experiment))  # the feeder loads and has every agent's bus
    try:  # the DMO's messages can carry every price the ISO's curve may set
        experiment.market.iso_curve.check_prices(load_case(experiment.market.case).grid.iso_price, PRICE_FLOOR,
                                                 PRICE_CAP)
    except ValueError as exc:
        raise ExperimentError(f"market: {exc}") from None
    return fleet


def agent_list(fleet: list[FleetMember]) -> str:
    """The fleet's agent ids for a line of text: all of a small fleet, the first and last of a large one."""
    ids = [m.id for m in fleet]
    return ", ".join(ids) if len(ids) <= 8 else f"{', '.join(ids[:3])}, ... {ids[-1]}"
