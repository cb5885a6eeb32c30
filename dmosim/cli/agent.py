"""``dmosim agent``: one microgrid agent role, for days spread over several hosts."""

from __future__ import annotations

import argparse

from messages.keys import check_run_id
from messages.transport import Bus
from scenarios.case import load_case
from scenarios.days import MAX_SEED
from scenarios.fleet import MAX_SCALE, MAX_SHIFT_HOURS, derive_case
from scenarios.generation import MAX_SCENARIOS

from ..console import UsageError
from .flags import add_bus_flags, add_fault_flags, add_method_flags, bus_config, check_bus_flags, check_fault_flags, message_faults, setup_logging
from ..arguments import gap, hours, integer, market_day, number, scales, seconds, seed, today

HELP = "one microgrid agent role"


def add_schedule_flags(p: argparse.ArgumentParser) -> None:
    """How the agent schedules its days."""
    p.add_argument("--scenarios", type=integer(1, MAX_SCENARIOS), default=5,
                   help=f"scenarios of each agent's schedule, at most {MAX_SCENARIOS} (default: 5)")
    p.add_argument("--gap", type=gap, default=0.01, help="relative MIP gap of each agent's schedule (default: 0.01)")
    p.add_argument("--time-limit", type=seconds, default=600.0, help="seconds per agent solve (default: 600)")
    p.add_argument("--load-scale", type=scales, default=(), metavar="X,Y,...",
                   help="each day's fixed-load forecast times these, day after day, repeated (e.g. a week: "
                        "1,1,1,1,1,0.8,0.8; default: 1)")
    p.add_argument("--renewable-scale", type=scales, default=(), metavar="X,Y,...",
                   help="each day's renewable forecasts times these, as --load-scale (default: 1)")
    add_method_flags(p, workers=1)  # the agents of one machine share its cores


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--id", required=True, help="agent id, e.g. mg1")
    p.add_argument("--run-id", help="the run to join: the id its DMO (or router) was given or printed (required)")
    p.add_argument("--case", default="paper", help="the microgrid's case (default: paper)")
    p.add_argument("--scale", type=number(0, MAX_SCALE, above=True), default=1.0,
                   help=f"size multiplier of the case, in (0, {MAX_SCALE:g}] (default: 1)")
    p.add_argument("--shift-hours", type=integer(-MAX_SHIFT_HOURS, MAX_SHIFT_HOURS), default=0,
                   help="shift of the load and renewable profiles (default: 0)")
    p.add_argument("--seed", type=seed, default=0,
                   help=f"seed of the agent's scenarios and realised day, 0..{MAX_SEED}")
    p.add_argument("--island-hours", type=hours, default=1, help="islanding hours the schedule plans for (default: 1)")
    p.add_argument("--market-day", type=market_day, default=None, help="the market day (default: today)")
    p.add_argument("--idle-timeout", type=seconds, default=3600.0, help="give up after this long without news")
    p.add_argument("--quiet", action="store_true")
    add_schedule_flags(p)
    add_fault_flags(p)
    add_bus_flags(p, "client")


def run(args) -> int:
    from microgrid_agent.agent.process import AgentConfig, MicrogridAgent  # noqa: PLC0415  (the solver stack)

    check_bus_flags(args, "client")
    check_fault_flags(args)
    if args.run_id is None:
        raise UsageError("--run-id is required: the id of the run to join, as its DMO (or router) printed it")
    try:
        check_run_id(args.run_id)
    except ValueError as exc:
        raise UsageError(f"--run-id: {exc}") from None
    setup_logging(args.id, args.quiet)
    name = args.case if args.scale == 1 else f"{args.case}x{args.scale:g}"
    case = derive_case(load_case(args.case), args.scale, args.shift_hours, name)
    config = AgentConfig(scenarios=args.scenarios, island_hours=args.island_hours, gap=args.gap,
                         time_limit=args.time_limit, seed=args.seed, idle_s=args.idle_timeout, method=args.method,
                         workers=args.workers, load_scale=args.load_scale, renewable_scale=args.renewable_scale)
    with Bus(args.run_id, args.id, bus_config(args, "client", args.id),
             faults=message_faults(args, args.run_id, args.id)) as bus:
        MicrogridAgent(bus, case, config, args.market_day or today()).run()
    return 0
