"""``dmosim dmo``: the market operator role alone, for days spread over several hosts (the Zenoh router by default)."""

from __future__ import annotations

import argparse
import json
import logging
import threading
from pathlib import Path

from messages.transport import Bus
from scenarios.case import load_case

from ..operator.config import DayConfig, islanding_by_day
from ..operator.day import MarketDay
from .flags import (SETTLEMENT_HELP, add_bus_flags, add_fault_flags, agent_ids, bus_config, credentials_for, hours,
                    market_day, message_faults, nonneg_float, positive_int, settlement_flag, setup_logging, today)

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
    p.add_argument("--penalty", type=nonneg_float, default=None, help="$/MWh above the award (default: the case's)")
    p.add_argument("--subperiods", type=positive_int, default=6, help="metering sub-periods per hour (default: 6)")
    p.add_argument("--seed", type=int, default=0, help="seed of the day (islanding, fleet) (default: 0)")
    p.add_argument("--market-day", type=market_day, default=None,
                   help="the (first) market day, YYYY-MM-DD (default: today)")
    p.add_argument("--days", type=positive_int, default=1,
                   help="consecutive market days in the run, each from the call for bids to settlement; agents "
                        "register once and carry their state across midnight (default: 1)")
    for name, default, what in (("registration", 60.0, "registration"), ("bid", 600.0, "bids"),
                                ("schedule", 1800.0, "schedules"), ("hour", 300.0, "each hour's meter reports")):
        p.add_argument(f"--{name}-timeout", type=nonneg_float, default=default, metavar="S",
                       help=f"deadline for {what}, seconds (default: {default:g})")
    p.add_argument("--quiet", action="store_true", help="log warnings only")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--agents", type=positive_int, required=True, help="agents to wait for at registration")
    p.add_argument("--fleet", help="fleet TOML file naming the agents the credentials are made for (default: "
                                   "mg1..mgN)")
    p.add_argument("--run-id", default="day", help="key prefix shared with the agents (default: day)")
    add_day_flags(p)
    p.add_argument("--credit", type=nonneg_float, default=0.0, help="$/MWh credited below the award (default: 0)")
    p.add_argument("--settlement", metavar="RULE", help=SETTLEMENT_HELP)
    p.add_argument("--import-limit", type=nonneg_float, default=None, help="feeder import limit, MW (default: 8 x agents)")
    p.add_argument("--export-limit", type=nonneg_float, default=None, help="feeder export limit, MW (default: 5 x agents)")
    p.add_argument("--result", help="write the day's JSON result here (default: stdout)")
    p.add_argument("--journal", metavar="PATH",
                   help="journal the day here; a DMO restarted with the same journal, run id and market day "
                        "resumes the day from it (docs/faults.md)")
    p.add_argument("--await-recorder", type=nonneg_float, default=0.0, metavar="S",
                   help="wait up to S seconds for a recorder of this run before the first message (default: 0, "
                        "do not wait)")
    add_fault_flags(p)
    add_bus_flags(p)


def day_config(args) -> DayConfig:
    case = load_case(args.case)
    return DayConfig(
        market_day=args.market_day or today(), agents=args.agents, iso_price=tuple(case.grid.iso_price),
        import_limit=args.import_limit if args.import_limit is not None else 8.0 * args.agents,
        export_limit=args.export_limit if args.export_limit is not None else 5.0 * args.agents,
        penalty=case.grid.penalty if args.penalty is None else args.penalty, credit=args.credit,
        subperiods=args.subperiods, islanded_hours=(), days=args.days,
        islanding_by_day=islanding_by_day(args.island_hours, args.seed, args.days),
        fixed_awards=tuple(case.grid.p_sch) if args.market == "fixed" else None,
        registration_s=args.registration_timeout, bids_s=args.bid_timeout, schedule_s=args.schedule_timeout,
        hour_s=args.hour_timeout, journal=args.journal, settlement=settlement_flag(args.settlement))


def run(args) -> int:
    setup_logging("dmo", args.quiet)
    config = day_config(args)
    credentials_for(args, args.run_id, agent_ids(args.fleet, args.agents), dmo_client=False)
    progress = lambda phase, hour: log.info("phase %s%s", phase, f" hour {hour}/24" if hour else "")  # noqa: E731
    with Bus(args.run_id, "dmo", bus_config(args, "router", "dmo", args.run_id)) as bus:
        bus.faults = message_faults(args, bus)
        before_start = (lambda: await_recorder(bus, args.await_recorder)) if args.await_recorder else None
        result = MarketDay(bus, config, progress).run(before_start)
        transport = bus.stats() | ({"faults_injected": bus.faults.summary()} if bus.faults else {})
    text = json.dumps(result.report(args.run_id, transport), indent=2)
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
