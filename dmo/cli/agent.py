"""``dmosim agent``: one microgrid agent role, for days spread over several hosts."""

from __future__ import annotations

import argparse

from messages.transport import Bus
from scenarios.case import load_case
from scenarios.fleet import derive_case

from .flags import (add_bus_flags, add_fault_flags, add_method_flags, bus_config, gap, hours, market_day,
                    message_faults, nonneg_float, positive_int, scales, setup_logging, today)

HELP = "one microgrid agent role"


def add_schedule_flags(p: argparse.ArgumentParser) -> None:
    """How the agent schedules its days."""
    p.add_argument("--scenarios", type=positive_int, default=5, help="scenarios of each agent's schedule (default: 5)")
    p.add_argument("--gap", type=gap, default=0.01, help="relative MIP gap of each agent's schedule (default: 0.01)")
    p.add_argument("--time-limit", type=nonneg_float, default=600.0, help="seconds per agent solve (default: 600)")
    p.add_argument("--load-scale", type=scales, default=(), metavar="X,Y,...",
                   help="each day's fixed-load forecast times these, day after day, repeated (e.g. a week: "
                        "1,1,1,1,1,0.8,0.8; default: 1)")
    p.add_argument("--renewable-scale", type=scales, default=(), metavar="X,Y,...",
                   help="each day's renewable forecasts times these, as --load-scale (default: 1)")
    add_method_flags(p, workers=1)  # the agents of one machine share its cores


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--id", required=True, help="agent id, e.g. mg1")
    p.add_argument("--run-id", default="day", help="key prefix shared with the DMO (default: day)")
    p.add_argument("--case", default="paper", help="the microgrid's case (default: paper)")
    p.add_argument("--scale", type=nonneg_float, default=1.0, help="size multiplier of the case (default: 1)")
    p.add_argument("--shift-hours", type=int, default=0, help="shift of the load and renewable profiles (default: 0)")
    p.add_argument("--seed", type=int, default=0, help="seed of the agent's scenarios and realised day")
    p.add_argument("--island-hours", type=hours, default=1, help="islanding hours the schedule plans for (default: 1)")
    p.add_argument("--market-day", type=market_day, default=None, help="the market day (default: today)")
    p.add_argument("--idle-timeout", type=nonneg_float, default=3600.0, help="give up after this long without news")
    p.add_argument("--quiet", action="store_true")
    add_schedule_flags(p)
    add_fault_flags(p)
    add_bus_flags(p)


def run(args) -> int:
    from microgrid_agent.agent.process import AgentConfig, MicrogridAgent  # noqa: PLC0415  (the solver stack)

    setup_logging(args.id, args.quiet)
    name = args.case if args.scale == 1 else f"{args.case}x{args.scale:g}"
    case = derive_case(load_case(args.case), args.scale, args.shift_hours, name)
    config = AgentConfig(scenarios=args.scenarios, island_hours=args.island_hours, gap=args.gap,
                         time_limit=args.time_limit, seed=args.seed, idle_s=args.idle_timeout, method=args.method,
                         workers=args.workers, load_scale=args.load_scale, renewable_scale=args.renewable_scale)
    with Bus(args.run_id, args.id, bus_config(args, "client", args.id)) as bus:
        bus.faults = message_faults(args, bus)
        MicrogridAgent(bus, case, config, args.market_day or today()).run()
    return 0
