"""What each role of a run takes from the resolved experiment: the DMO its days (``DayConfig``), an agent its member
of the fleet, its case and how it schedules (``AgentConfig``), every role the message faults it applies.

``dmosim run`` writes the resolved experiment into the run directory and starts each role with that file
(``--experiment``); a role started by hand reads the same file, or none (the defaults of spec.py), and its flags
override it. Every setting's default is the one of spec.py: nothing here has a default of its own.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import functools
from pathlib import Path

from dmo.market.choice import choose
from dmo.market.clearing import IsoCurve
from dmo.operator.config import LOGICAL, DayConfig, islanding_by_day
from messages.transport.faults import MessageFault
from scenarios.case import load_case
from scenarios.diverse import generate_fleet
from scenarios.fleet import CASES_DIR, FleetMember, load_fleet, make_fleet, write_fleet
from scenarios.names import DMO
from scenarios.network import NETWORKS, Network, NetworkError, load_network, voltage_band

from ..experiment.spec import Agents, Experiment, ExperimentError, with_market_terms
from .faults import Fault, parse_fault

IMPORT_LIMIT_PER_AGENT = 8.0  # MW of feeder import per agent, where the experiment sets no import limit
EXPORT_LIMIT_PER_AGENT = 5.0  # MW of feeder export per agent, where the experiment sets no export limit
# hosting = "auto" (docs/benchmarks.md, "Hosting agents"): on 2 cores a day of 4 tiny agents took 14.1 s as processes
# and 13.8 s forked, of 12 agents 46.8 s and 16.5 s (each process importing the solver stack for 23 s of
# registration), of 60 agents 195 s (82 s of registration) and 72 s forked ten to a process
PROCESSES_UP_TO = 4
FORKED_PROCESSES = 8


def resolved(experiment: Experiment) -> Experiment:
    """The experiment as a run fixes it: its market day (today if it named none) and its fleet and network files as
    absolute paths, so each role reads the same run from the run directory's copy, whatever directory it starts in."""
    update = {}
    if experiment.market_day is None:
        update["market_day"] = dt.date.today().isoformat()
    fleet = experiment.agents.fleet
    if fleet is not None and not Path(fleet).is_absolute():
        update["agents"] = experiment.agents.model_copy(update={"fleet": str(Path(fleet).resolve())})
    feeder = experiment.network.feeder
    if feeder is not None and feeder not in NETWORKS and not Path(feeder).is_absolute():
        update["network"] = experiment.network.model_copy(update={"feeder": str(Path(feeder).resolve())})
    out = experiment.model_copy(update=update) if update else experiment
    if feeder is None:
        return out
    fleet, buses = fleet_of(out), out.network.buses
    if len(buses) != len(fleet) or any(m.bus not in (None, b) for m, b in zip(fleet, buses)):
        # every agent's bus, written down once: each role then reads its own without loading the feeder
        placement = placement_of(out, network_of(out))
        out = out.model_copy(update={"network": out.network.model_copy(update={"buses": list(placement.values())})})
    return out


def hosting_of(agents: Agents, count: int, cluster: bool = False) -> tuple[str, int]:
    """How ``dmosim run`` hosts ``count`` agents, and how many to a forked process: as ``agents`` says, or with
    ``hosting = "auto"`` each a process of its own up to ``PROCESSES_UP_TO`` agents, else forked from one host that
    has imported their code, at most ``FORKED_PROCESSES`` processes of them (on a cluster, one agent to a process:
    each worker forks its own)."""
    if agents.hosting != "auto":
        return agents.hosting, agents.per_process or 1
    if count <= PROCESSES_UP_TO:
        return "process", 1
    return "fork", 1 if cluster else -(-count // FORKED_PROCESSES)


def bus_of(experiment: Experiment, member: FleetMember) -> str | None:
    """The bus the agent registers at: its place in the resolved experiment's ``network.buses`` (None on the
    copper plate)."""
    if experiment.network.feeder is None:
        return None
    return experiment.network.buses[[m.id for m in fleet_of(experiment)].index(member.id)]


def network_of(experiment: Experiment) -> Network | None:
    """The feeder the run's market clears on, at the experiment's load scale (None: the copper plate), checked as
    the DMO will clear it; ExperimentError, one line, if it cannot be used."""
    n, m = experiment.network, experiment.market
    if n.feeder is None:
        return None
    iso_price = tuple(load_case(m.case).grid.iso_price)
    return _feeder(n.feeder, n.load_scale, n.voltage_margin, iso_price, *substation_limits(experiment), m.iso_curve,
                   n.clearing, n.spill_price)


@functools.lru_cache(maxsize=4)  # a run resolves, checks and configures its DMO from one feeder: load it once
def _feeder(source: str, load_scale: float, margin: float, iso_price: tuple[float, ...], import_limit: float,
            export_limit: float, curve: IsoCurve, method: str, spill_price: float) -> Network:
    """The feeder loaded and cleared once with no bids on the DMO's own terms (its ISO prices, the substation's
    limits, the ISO's curve, the voltage margin, its clearing method and spill price): what no clearing of the run can serve, even shedding all its fixed
    load and spilling all its fixed generation, fails here and not in the DMO (a bus's v_min above the substation's
    voltage). Bids only add what may also be 0."""
    from dmo.market.distflow import clear_network  # noqa: PLC0415  (scipy's LP: 40 MiB no copper-plate role needs)

    try:
        network = load_network(source, load_scale=load_scale)
        voltage_band(network, margin)  # a margin that leaves a bus no band fails here, not in the DMO
    except NetworkError as exc:
        raise ExperimentError(f"network.feeder: {exc}") from None
    try:
        clear_network([], network, {}, iso_price, import_limit, export_limit, margin=margin, curve=curve,
                      method=method, spill_price=spill_price)
    except ValueError as exc:
        raise ExperimentError(f"network.feeder: {exc}, within the substation's import limit {import_limit:g} MW and "
                              f"export limit {export_limit:g} MW (market.import_limit, market.export_limit)") from None
    return network


def substation_limits(experiment: Experiment) -> tuple[float, float]:
    """The market's import and export limits at the substation, MW: the experiment's, else per agent."""
    m, agents = experiment.market, len(fleet_of(experiment))
    return (m.import_limit if m.import_limit is not None else IMPORT_LIMIT_PER_AGENT * agents,
            m.export_limit if m.export_limit is not None else EXPORT_LIMIT_PER_AGENT * agents)


def placement_of(experiment: Experiment, network: Network | None) -> dict[str, str]:
    """Agent -> its bus (docs/network.md, "Placing the agents"): its fleet entry's bus, else ``network.buses`` by
    its position in the fleet, else spread: agent i of n at the feeder's non-substation bus i x m / n (m of them, in
    the feeder's order). Empty on the copper plate, where a bus is an ExperimentError; so is a bus the feeder lacks,
    or its substation."""
    fleet, given = fleet_of(experiment), experiment.network.buses
    if network is None:
        if given or any(m.bus for m in fleet):
            raise ExperimentError("network.buses or a fleet's bus places agents on a feeder, but network.feeder "
                                  "names none")
        return {}
    if len(given) > len(fleet):
        raise ExperimentError(f"network.buses: {len(given)} buses for {len(fleet)} agents")
    free = [b for i, b in enumerate(network.buses) if i != network.root]
    out = {}
    for i, m in enumerate(fleet):
        bus = m.bus or (given[i] if i < len(given) else free[i * len(free) // len(fleet)])
        try:
            network.bus_of(bus, f"the bus of {m.id}")
        except NetworkError as exc:
            raise ExperimentError(str(exc)) from None
        out[m.id] = bus
    return out


def fleet_of(experiment: Experiment) -> list[FleetMember]:
    """The agents of the run: the members of its fleet file, else the diverse fleet it generates, else mg1..mgN
    drawn from its seed."""
    a = experiment.agents
    if a.fleet:
        return load_fleet(a.fleet)
    if a.generate is not None:
        return generate_fleet(a.generate, seed=experiment.seed)
    return make_fleet(a.count, seed=experiment.seed)


def placed_fleet(experiment: Experiment) -> list[FleetMember]:
    """The agents of a (resolved) experiment (``fleet_of``), each at the bus the experiment places it at on its
    feeder, if it has one (``network.buses``: every agent's, once resolved)."""
    fleet = fleet_of(experiment)
    if experiment.network.feeder is None:
        return fleet
    return [dataclasses.replace(m, bus=bus) for m, bus in zip(fleet, experiment.network.buses)]


def fleet_written(experiment: Experiment, path: Path) -> Experiment:
    """A (resolved) experiment that generates its fleet (``agents.generate``), with that fleet written as the fleet
    file ``path`` and its cases beside it (``scenarios.fleet.write_fleet``), each member at the bus the experiment
    places it at, and ``agents.fleet`` naming the file instead: the experiment every role of the run then reads,
    which nothing else need know was generated. Any other experiment as it is."""
    a = experiment.agents
    if a.generate is None:
        return experiment
    fleet = placed_fleet(experiment)
    comment = (f"dmosim fleet: {a.generate} microgrids drawn from {fleet[0].case} with seed {experiment.seed} "
               f"(docs/agent.md, \"Generated fleets\"); each case file is in {CASES_DIR}/")
    written = write_fleet(fleet, path, comment)
    return experiment.model_copy(update={"agents": a.model_copy(update={"generate": None,
                                                                        "fleet": str(written.resolve())})})


def strategy_of(experiment: Experiment, member: FleetMember) -> str:
    """The strategy an agent bids with (docs/strategies.md): its fleet entry's, else the experiment's."""
    return member.strategy or experiment.agents.strategy


def member_of(experiment: Experiment, agent_id: str) -> FleetMember:
    """Agent ``agent_id`` of the run; an id the run has no agent of is an ExperimentError."""
    fleet = fleet_of(experiment)
    for member in fleet:
        if member.id == agent_id:
            return member
    names = f"{fleet[0].id}..{fleet[-1].id}" if len(fleet) > 3 else ", ".join(m.id for m in fleet)
    raise ExperimentError(f"{agent_id} is not an agent of the experiment ({names}; --agents N or --fleet FILE)")


def agent_config(experiment: Experiment, member: FleetMember):
    """How ``member`` schedules its days (``AgentConfig``): the experiment's schedule settings and profiles, the
    islanding hours the market announces, the member's own seed."""
    from microgrid_agent.agent.machine import AgentConfig  # noqa: PLC0415  (the solver stack: for agents only)

    s, p = experiment.schedule, experiment.profiles
    return AgentConfig(scenarios=s.scenarios, island_hours=experiment.market.island_hours, gap=s.gap,
                       time_limit=s.time_limit, seed=member.seed, method=s.method, workers=s.workers,
                       load_scale=tuple(p.load_scale), renewable_scale=tuple(p.renewable_scale),
                       bus=bus_of(experiment, member),
                       **(dict(statement_s=None, receipts_s=None) if experiment.deadlines.clock == LOGICAL else {}))


def day_config(experiment: Experiment, *, journal: str | None = None) -> DayConfig:
    """The DMO's days of the (resolved) experiment; a settlement rule of the user's own is loaded here (the run
    checked that it may be), and a rule whose parameters disagree with the market's is a ValueError."""
    e, m, d = experiment, experiment.market, experiment.deadlines
    case = load_case(m.case)
    agents = len(fleet_of(e))
    network = network_of(e)
    rule = None if m.settlement is None else with_market_terms(choose(m.settlement), m, case.grid.penalty)
    import_limit, export_limit = substation_limits(e)
    return DayConfig(
        market_day=e.market_day, agents=agents, iso_price=tuple(case.grid.iso_price),
        import_limit=import_limit, export_limit=export_limit,
        penalty=case.grid.penalty if m.penalty is None else m.penalty, credit=m.credit, subperiods=m.subperiods,
        islanded_hours=(), days=e.days, islanding_by_day=islanding_by_day(m.island_hours, e.seed, e.days),
        fixed_awards=tuple(case.grid.p_sch) if m.mode == "fixed" else None,
        registration_s=d.registration, bids_s=d.bid, schedule_s=d.schedule, hour_s=d.hour, clock=d.clock,
        journal=journal,
        settlement=rule, network=network, placement=placement_of(e, network),
        voltage_margin=e.network.voltage_margin, clearing=e.network.clearing, spill_price=e.network.spill_price,
        iso_curve=m.iso_curve,
        restarting=frozenset(f.agent for f in map(parse_fault, e.faults) if isinstance(f, Fault) and f.kind == "restart"
                             and f.agent != DMO))


def message_faults(experiment: Experiment) -> list[MessageFault]:
    """The experiment's faults on messages: every role applies those that match what it publishes (the launcher
    fires the faults on processes)."""
    return [f for f in map(parse_fault, experiment.faults) if isinstance(f, MessageFault)]
