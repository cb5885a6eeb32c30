"""The experiment's settings as flags: ``dmosim run`` takes them all, ``dmosim dmo`` and ``dmosim agent`` those of
their role. Each flag overrides the experiment file's setting (``--experiment``, or ``run``'s EXPERIMENT); its
default, shown in its help, is the experiment's (dmosim/experiment/spec.py), defined there once.
"""

from __future__ import annotations

import argparse
from typing import Iterable

from dmo.market.clearing import CLEARING_METHODS
from dmo.market.rules import MAX_MW, MAX_RATE
from dmo.operator.config import CLOCKS
from messages.schemas import MAX_AGENTS, MAX_DAYS, MAX_SUBPERIODS, PRICE_CAP
from messages.transport.credentials import MAX_HOSTS
from microgrid_agent.solvers.routes import METHODS, auto_rule
from scenarios.days import MAX_SEED
from scenarios.fleet import MAX_SCALE, FleetError
from scenarios.generation import MAX_SCENARIOS
from scenarios.network import NETWORKS

from ..console import UsageError
from ..arguments import gap, hours, integer, market_day, number, scales, seconds, seed
from ..experiment.spec import (FLAGS, HOSTINGS, MAX_VOLTAGE_MARGIN, MAX_WORKERS, Experiment, ExperimentError,
                               load_experiment, with_settings)
from ..launch.roles import (EXPORT_LIMIT_PER_AGENT, FORKED_PROCESSES, IMPORT_LIMIT_PER_AGENT, PROCESSES_UP_TO,
                            fleet_of, resolved)
from .flags import SETTLEMENT_HELP, STRATEGY_HELP

DEADLINES = (("registration", "registration"), ("bid", "bids"), ("schedule", "schedules"),
             ("hour", "each hour's meter reports"))
# The settings of each role: what it reads of the experiment and may be told on its command line.
RUN_SETTINGS = ("agents.count", "agents.fleet", "agents.generate", "days", "market_day", "seed")
MARKET_SETTINGS = tuple(k for k in FLAGS if k.startswith("market."))
NETWORK_SETTINGS = tuple(k for k in FLAGS if k.startswith("network."))
DMO_SETTINGS = RUN_SETTINGS + MARKET_SETTINGS + NETWORK_SETTINGS + ("deadlines.clock",) + tuple(
    f"deadlines.{name}" for name, _ in DEADLINES)
AGENT_SETTINGS = RUN_SETTINGS + ("agents.strategy", "market.island_hours", "network.feeder") + tuple(
    k for k in FLAGS if k.startswith(("schedule.", "profiles.")))


def _flags(default: Experiment) -> dict[str, tuple[str, dict]]:
    """Setting -> (flag, add_argument keywords), every default as the experiment ``default`` has it."""
    m, s = default.market, default.schedule
    flags = {
        "agents.count": ("--agents", dict(type=integer(1, MAX_AGENTS),
                                         help=f"agents mg1..mgN (default: {default.agents.count})")),
        "agents.fleet": ("--fleet", dict(help="fleet TOML file naming the agents and their cases (instead of "
                                              "--agents)")),
        "agents.generate": ("--generate", dict(type=integer(1, MAX_AGENTS), metavar="N", help=(
            "N diverse agents mg1..mgN drawn from --seed (sizes, unit mixes, renewables, storage, load shapes: "
            "docs/agent.md, \"Generated fleets\"), written into the run directory as fleet.toml (instead of "
            "--agents)"))),
        "agents.strategy": ("--strategy", dict(metavar="SPEC", help=STRATEGY_HELP.replace(
            "default: price-response", f"default: {default.agents.strategy}; a fleet entry's own overrides it"))),
        "agents.hosting": ("--hosting", dict(choices=HOSTINGS, help=(
            "how the agents' processes start: process, each a Python of its own; fork, forked from one process that "
            "has loaded their code, which they share (less memory and start-up for large fleets: docs/benchmarks.md, "
            f"\"Hosting agents\"); auto, process up to {PROCESSES_UP_TO} agents, else fork, at most "
            f"{FORKED_PROCESSES} processes of agents; in-process, the DMO, every agent and the recorder in this one "
            "process with no network, on the logical clock, several times faster, without faults, routers or "
            "agents of other languages (docs/experiments.md, \"In one process\"); the results are the same "
            f"(default: {default.agents.hosting})"))),
        "agents.per_process": ("--per-process", dict(type=integer(1, MAX_AGENTS), metavar="K", help=(
            "with --hosting fork, K agents in each forked process, a thread each: the pages a process copies from "
            "the host are paid once per K agents; an agent a kill or restart fault names runs alone "
            "(default: 1, or as --hosting auto chooses)"))),
        "agents.routers": ("--routers", dict(type=integer(0, MAX_HOSTS), metavar="N", help=(
            "start N Zenoh routers on this machine, each standing for one host's (docs/hosts.md): the DMO and the "
            "recorder are clients of the first, the agents of all N in blocks; more than one form a mesh over "
            f"mutual TLS; 0: the DMO is the agents' router (default: {default.agents.routers})"))),
        "days": ("--days", dict(type=integer(1, MAX_DAYS),
                                help="consecutive market days; agents register once and carry their state across "
                                     f"midnight (at most {MAX_DAYS}; default: {default.days})")),
        "market_day": ("--market-day", dict(type=market_day, help="the first market day, YYYY-MM-DD "
                                                                  "(default: today)")),
        "seed": ("--seed", dict(type=seed, help="seed of the run: fleet, forecast errors, islanding, faults, "
                                                f"0..{MAX_SEED} (default: {default.seed})")),
        "market.case": ("--case", dict(help=f"case giving the ISO price, penalty and Table I awards "
                                            f"(default: {m.case})")),
        "market.mode": ("--market", dict(choices=("bids", "fixed"),
                                         help="bids: clear the agents' bids; fixed: award the case's Table I to "
                                              f"every agent (default: {m.mode})")),
        "market.penalty": ("--penalty", dict(type=number(0, MAX_RATE),
                                             help="$/MWh above the award (default: the case's)")),
        "market.credit": ("--credit", dict(type=number(0, MAX_RATE),
                                           help=f"$/MWh below the award (default: {m.credit:g})")),
        "market.settlement": ("--settlement", dict(metavar="RULE", help=SETTLEMENT_HELP)),
        "market.import_limit": ("--import-limit", dict(type=number(0, MAX_MW), help="feeder import limit, MW "
                                                       f"(default: {IMPORT_LIMIT_PER_AGENT:g} x agents)")),
        "market.export_limit": ("--export-limit", dict(type=number(0, MAX_MW), help="feeder export limit, MW "
                                                       f"(default: {EXPORT_LIMIT_PER_AGENT:g} x agents)")),
        "market.island_hours": ("--island-hours", dict(type=hours, help="hours each day is islanded (default: "
                                                                        f"{m.island_hours})")),
        "market.subperiods": ("--subperiods", dict(type=integer(1, MAX_SUBPERIODS),
                                                   help=f"metering sub-periods per hour, at most {MAX_SUBPERIODS} "
                                                        f"(default: {m.subperiods})")),
        "schedule.scenarios": ("--scenarios", dict(type=integer(1, MAX_SCENARIOS),
                                                   help=f"scenarios of each agent's schedule, at most "
                                                        f"{MAX_SCENARIOS} (default: {s.scenarios})")),
        "schedule.gap": ("--gap", dict(type=gap, help=f"relative MIP gap of each schedule (default: {s.gap:g})")),
        "schedule.time_limit": ("--time-limit", dict(type=seconds, help=(
            "seconds at most per agent solve: a solve cut by it gives a schedule that depends on how busy the machine "
            "is (default: none, the gap alone ends a solve)"))),
        "schedule.method": ("--method", dict(choices=METHODS,
                                             help="route of the agents' solves: extensive, one MILP; benders, "
                                                  "decomposed (docs/solver.md); tree, decomposed in one SCIP tree "
                                                  f"(pip install 'dmosim[scip]'); auto, {auto_rule()} "
                                                  f"(default: {s.method})")),
        "schedule.workers": ("--workers", dict(type=integer(1, MAX_WORKERS),
                                               help=f"processes per agent for Benders subproblems, at most "
                                                    f"{MAX_WORKERS} (default: {s.workers})")),
        "profiles.load_scale": ("--load-scale", dict(type=scales, metavar="X,Y,...",
                                                     help="each day's fixed-load forecast times these, repeated "
                                                          "over the days (default: 1)")),
        "profiles.renewable_scale": ("--renewable-scale", dict(type=scales, metavar="X,Y,...",
                                                               help="each day's renewable forecasts times these, as "
                                                                    "--load-scale (default: 1)")),
        "network.feeder": ("--feeder", dict(metavar="NETWORK", help=(
            f"clear on this feeder, a built-in ({', '.join(NETWORKS)}) or a network file (TOML or pandapower "
            "JSON; docs/network.md), each agent at its bus (default: none, the copper plate)"))),
        "network.load_scale": ("--network-load-scale", dict(type=number(0, MAX_SCALE, above=True), metavar="X", help=(
            f"the feeder's fixed loads times this (default: {default.network.load_scale:g})"))),
        "network.voltage_margin": ("--voltage-margin", dict(type=number(0, MAX_VOLTAGE_MARGIN), metavar="PU", help=(
            "p.u. the clearing keeps inside every bus's voltage limits, for what LinDistFlow neglects "
            f"(default: {default.network.voltage_margin:g})"))),
        "network.clearing": ("--clearing", dict(choices=CLEARING_METHODS, help=(
            "on a feeder, clear on the AC flow linearised at its own plan, priced with its losses (ac), or on "
            f"LinDistFlow alone (lindistflow; docs/market.md, \"AC-faithful clearing\"; default: "
            f"{default.network.clearing})"))),
        "network.spill_price": ("--spill-price", dict(type=number(0, PRICE_CAP), metavar="USD", help=(
            "on a feeder, $/MWh that spilling a MW of its fixed generation costs, when no line can carry it "
            f"(docs/market.md; default: {default.network.spill_price:g})"))),
    }
    flags["deadlines.clock"] = ("--clock", dict(choices=CLOCKS, help=(
        "how a phase ends: logical, when every live agent has answered, however long that takes, so a busy machine "
        "makes a run slower, never different; wall, at the latest at its deadline (--*-timeout), for roles started "
        "by hand that may never come and agents of other languages (docs/experiments.md, \"Logical and wall-clock "
        f"time\"; default: {default.deadlines.clock})")))
    for name, what in DEADLINES:
        flags[f"deadlines.{name}"] = (f"--{name}-timeout", dict(
            type=seconds, metavar="S", help=f"with --clock wall, deadline for {what}, s (default: "
                                            f"{getattr(default.deadlines, name):g})"))
    return flags


def add_setting_flags(group, keys: Iterable[str]) -> None:
    """The flags of the settings ``keys`` (dotted, as in an experiment file), on a parser or argument group."""
    flags = _flags(Experiment())
    for key in keys:
        flag, kwargs = flags[key]
        group.add_argument(flag, dest=FLAGS[key], **kwargs)


def add_experiment_flag(p: argparse.ArgumentParser, keys: Iterable[str]) -> None:
    """``--experiment FILE`` for a role, and the flags of its settings, which override the file."""
    p.add_argument("--experiment", metavar="FILE",
                   help="the run's experiment (TOML, docs/experiments.md): the experiment.toml of the run directory "
                        "for a role of a dmosim run (default: the defaults below)")
    add_setting_flags(p.add_argument_group("the experiment (each overrides --experiment; default: its setting, "
                                           "else shown)"), keys)


def settings_given(args) -> dict[str, object]:
    """Dotted setting -> value, of every setting flag the command line gave (lists where the experiment has them)."""
    given = {key: getattr(args, dest) for key, dest in FLAGS.items() if getattr(args, dest, None) is not None}
    return {key: list(value) if isinstance(value, tuple) else value for key, value in given.items()}


def experiment_with_flags(base: Experiment, args) -> Experiment:
    """``base`` with the settings the flags give; ExperimentError if they contradict it (a count beside a fleet)."""
    given = settings_given(args)
    fleet = given.get("agents.fleet") or base.agents.fleet
    if "agents.count" in given and fleet:
        raise ExperimentError(f"--agents and a fleet ({fleet}) exclude each other: a fleet file names its agents")
    if "agents.count" in given and (given.get("agents.generate") or base.agents.generate) is not None:
        # also --agents 3, which the experiment could not tell from its default
        raise ExperimentError(f"--agents and {'--generate' if 'agents.generate' in given else 'agents.generate'} "
                              "exclude each other: generate draws that many agents of its own")
    return with_settings(base, given, "flags") if given else base


def role_experiment(args) -> Experiment:
    """The experiment a role runs: ``--experiment FILE`` (else the defaults) with its flags given, resolved
    (``launch.roles.resolved``), its fleet read; what cannot be used is the one-line UsageError."""
    try:
        base = load_experiment(args.experiment) if args.experiment else Experiment()
        experiment = resolved(experiment_with_flags(base, args))
        fleet_of(experiment)  # a fleet file that cannot be read fails here, in one line
    except (ExperimentError, FleetError) as exc:
        raise UsageError(str(exc)) from None
    return experiment
