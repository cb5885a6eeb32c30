"""``dmosim dmo``: the market operator role alone, for days spread over several hosts (the Zenoh router by default)."""

from __future__ import annotations

import argparse
import json
import logging
import threading
from pathlib import Path

from messages.schemas import MAX_DAYS, MAX_SUBPERIODS
from messages.transport import Bus
from scenarios.case import load_case
from scenarios.days import MAX_SEED, market_days

from dmo.market.choice import ChosenRule
from dmo.market.rules import MAX_MW, MAX_RATE, market_parameters
from dmo.operator.config import DayConfig, islanding_by_day
from dmo.operator.day import MarketDay
from ..console import UsageError
from .flags import SETTLEMENT_HELP, add_bus_flags, add_fault_flags, agent_ids, announce_run_id, bus_config, check_bus_flags, check_fault_flags, credentials_for, message_faults, run_id_of, settlement_flag, setup_logging
from ..arguments import agents, hours, integer, market_day, number, seconds, seed, today, wait

HELP = "the market operator role alone (the Zenoh router by default)"
log = logging.getLogger("dmosim")


def add_day_flags(p: argparse.ArgumentParser) -> None:
    """Settings of the days the DMO runs."""
    p.add_argument("--case", default="paper",
                   help="case giving the ISO price, penalty and Table I awards (default: paper)")
    p.add_argument("--market", choices=("bids", "fixed"), default="bids",
                   help="bids: clear the agents' bids; fixed: award the case's Table I to every agent")
    p.add_argument("--island-hours", type=hours, default=1,
                   help="hours the feeder is islanded during the day (default: 1)")
    p.add_argument("--penalty", type=number(0, MAX_RATE), default=None,
                   help="$/MWh above the award (default: the case's)")
    p.add_argument("--subperiods", type=integer(1, MAX_SUBPERIODS), default=6,
                   help=f"metering sub-periods per hour, at most {MAX_SUBPERIODS} (default: 6)")
    p.add_argument("--seed", type=seed, default=0,
                   help=f"seed of the day (islanding, fleet), 0..{MAX_SEED} (default: 0)")
    p.add_argument("--market-day", type=market_day, default=None,
                   help="the (first) market day, YYYY-MM-DD (default: today)")
    p.add_argument("--days", type=integer(1, MAX_DAYS), default=1,
                   help="consecutive market days in the run, each from the call for bids to settlement; agents "
                        f"register once and carry their state across midnight (at most {MAX_DAYS}; default: 1)")
    for name, default, what in (("registration", 60.0, "registration"), ("bid", 600.0, "bids"),
                                ("schedule", 1800.0, "schedules"), ("hour", 300.0, "each hour's meter reports")):
        p.add_argument(f"--{name}-timeout", type=seconds, default=default, metavar="S",
                       help=f"deadline for {what}, seconds (default: {default:g})")
    p.add_argument("--quiet", action="store_true", help="log warnings only")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--agents", type=agents, help="agents to wait for at registration (default: those --fleet names)")
    p.add_argument("--fleet", help="fleet TOML file naming the agents the credentials are made for (default: "
                                   "mg1..mgN)")
    p.add_argument("--run-id", help="key prefix shared with the agents (default: a new one, printed)")
    add_day_flags(p)
    p.add_argument("--credit", type=number(0, MAX_RATE), default=0.0,
                   help="$/MWh credited below the award (default: 0)")
    p.add_argument("--settlement", metavar="RULE", help=SETTLEMENT_HELP)
    p.add_argument("--import-limit", type=number(0, MAX_MW), default=None,
                   help="feeder import limit, MW (default: 8 x agents)")
    p.add_argument("--export-limit", type=number(0, MAX_MW), default=None,
                   help="feeder export limit, MW (default: 5 x agents)")
    p.add_argument("--result", help="write the day's JSON result here (default: stdout)")
    p.add_argument("--journal", metavar="PATH",
                   help="journal the day here; a DMO restarted with the same journal, run id and market day "
                        "resumes the day from it (docs/faults.md)")
    p.add_argument("--await-recorder", type=wait, default=0.0, metavar="S",
                   help="wait up to S seconds for a recorder of this run before the first message (default: 0, "
                        "do not wait)")
    add_fault_flags(p)
    add_bus_flags(p, "router")


def day_config(args, agents: int) -> DayConfig:
    """The DMO's days as the flags set them, for ``agents`` agents; a bad combination is a UsageError."""
    case = load_case(args.case)
    first = args.market_day or today()
    try:
        market_days(first, args.days)
    except ValueError as exc:
        raise UsageError(f"--days: {exc}") from None
    return DayConfig(
        market_day=first, agents=agents, iso_price=tuple(case.grid.iso_price),
        import_limit=args.import_limit if args.import_limit is not None else 8.0 * agents,
        export_limit=args.export_limit if args.export_limit is not None else 5.0 * agents,
        penalty=case.grid.penalty if args.penalty is None else args.penalty, credit=args.credit,
        subperiods=args.subperiods, islanded_hours=(), days=args.days,
        islanding_by_day=islanding_by_day(args.island_hours, args.seed, args.days),
        fixed_awards=tuple(case.grid.p_sch) if args.market == "fixed" else None,
        registration_s=args.registration_timeout, bids_s=args.bid_timeout, schedule_s=args.schedule_timeout,
        hour_s=args.hour_timeout, journal=args.journal, settlement=settlement_rule(args, case.grid.penalty))


def settlement_rule(args, case_penalty: float) -> ChosenRule | None:
    """``--settlement`` beside ``--penalty`` and ``--credit``: a built-in rule with the parameters it settles by
    (``rules.market_parameters``: ``paper`` takes the rates it is not given from them), or the one-line UsageError
    where they disagree; a rule of one's own as named; None without ``--settlement``."""
    chosen = settlement_flag(args.settlement)
    if chosen is None or chosen.built_in is None:
        return chosen
    try:
        params = market_parameters(chosen.built_in, chosen.params, args.penalty, args.credit, case_penalty)
    except ValueError as exc:
        raise UsageError(f"--settlement: {exc}") from None
    return ChosenRule(chosen.name, chosen.rule, params)


def agent_names(args) -> list[str]:
    """The agents of the run: those ``--fleet`` names (``--agents``, if given too, must count them), else
    mg1..mgN for ``--agents N``."""
    if args.fleet is None and args.agents is None:
        raise UsageError("--agents N or --fleet FILE: the DMO waits for the agents they name")
    names = agent_ids(args.fleet, args.agents or 1)
    if args.fleet is not None and args.agents is not None and args.agents != len(names):
        raise UsageError(f"--agents {args.agents} beside --fleet {args.fleet}, which names {len(names)}: give one")
    return names


def run(args) -> int:
    setup_logging("dmo", args.quiet)
    names = agent_names(args)
    check_fault_flags(args)
    check_bus_flags(args, "router")
    config = day_config(args, len(names))
    run_id = run_id_of(args)
    credentials_for(args, run_id, names, dmo_client=False)
    settings = bus_config(args, "router", "dmo", run_id)
    announce_run_id(args)
    progress = lambda phase, hour: log.info("phase %s%s", phase, f" hour {hour}/24" if hour else "")  # noqa: E731
    with Bus(run_id, "dmo", settings, faults=message_faults(args, run_id, "dmo")) as bus:
        before_start = (lambda: await_recorder(bus, args.await_recorder)) if args.await_recorder else None
        result = MarketDay(bus, config, progress).run(before_start)
        transport = bus.stats() | ({"faults_injected": bus.faults_injected()} if bus.faults else {})
    text = json.dumps(result.report(run_id, transport), indent=2)
    if args.result:
        Path(args.result).write_text(text + "\n")
    else:
        print(text)
    return 0


def await_recorder(bus: Bus, timeout_s: float) -> None:
    """Block until the run's recorder is present (its token is declared after its subscription, so it listens)."""
    present = threading.Event()
    with bus.watch_presence(lambda name: name == "recorder" and present.set(), lambda name: None):
        if not present.wait(timeout_s):
            raise RuntimeError(f"no recorder joined run {bus.keys.run_id} within {timeout_s:g} s")
    log.info("recorder present")
