"""``dmosim agent``: one microgrid agent role, for days spread over several hosts."""

from __future__ import annotations

import argparse
import dataclasses

from messages.keys import check_run_id
from messages.transport import Bus
from scenarios.fleet import MAX_SCALE, MAX_SHIFT_HOURS, member_case

from ..arguments import integer, number, seconds
from ..console import UsageError
from ..experiment.spec import ExperimentError
from ..launch.roles import agent_config, member_of, strategy_of
from .flags import (add_bus_flags, add_fault_flags, bus_config, check_bus_flags, check_fault_flags, message_faults,
                    setup_logging)
from .settings import AGENT_SETTINGS, add_experiment_flag, role_experiment

HELP = "one microgrid agent role"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--id", required=True, help="agent id, e.g. mg1: the agent of the experiment's fleet it is")
    p.add_argument("--run-id", help="the run to join: the id its DMO (or router) was given or printed (required)")
    add_experiment_flag(p, AGENT_SETTINGS)
    member = p.add_argument_group("this agent (each overrides what the experiment's fleet says of it)")
    member.add_argument("--case", dest="member_case", metavar="CASE", help="the microgrid's base case, built in or a file")
    member.add_argument("--scale", type=number(0, MAX_SCALE, above=True),
                        help=f"size multiplier of the case, in (0, {MAX_SCALE:g}]")
    member.add_argument("--shift-hours", type=integer(-MAX_SHIFT_HOURS, MAX_SHIFT_HOURS),
                        help="shift of the load and renewable profiles, hours")
    p.add_argument("--idle-timeout", type=seconds, help="give up after this long without news from the DMO, s "
                                                        "(default: an hour)")
    p.add_argument("--quiet", action="store_true", help="log warnings only")
    add_fault_flags(p)
    add_bus_flags(p, "client")


def run(args) -> int:
    from microgrid_agent.agent.process import MicrogridAgent  # noqa: PLC0415  (the solver stack)
    from microgrid_agent.agent.strategies import StrategyError, choose_strategy  # noqa: PLC0415

    check_bus_flags(args, "client")
    check_fault_flags(args)
    if args.run_id is None:
        raise UsageError("--run-id is required: the id of the run to join, as its DMO (or router) printed it")
    try:
        check_run_id(args.run_id)
    except ValueError as exc:
        raise UsageError(f"--run-id: {exc}") from None
    experiment = role_experiment(args)
    try:
        member = member_of(experiment, args.id)
    except ExperimentError as exc:
        raise UsageError(str(exc)) from None
    given = {"case": args.member_case, "scale": args.scale, "shift_hours": args.shift_hours}
    member = dataclasses.replace(member, **{k: v for k, v in given.items() if v is not None})
    if args.member_case is not None:  # a case given replaces one drawn for a generated fleet's member
        member = dataclasses.replace(member, drawn=None)
    config = agent_config(experiment, member)
    if args.idle_timeout is not None:
        config = dataclasses.replace(config, idle_s=args.idle_timeout)
    setup_logging(args.id, args.quiet)
    case = member_case(member)
    try:  # made, and a strategy of the user's own tried, before the agent joins (docs/strategies.md)
        strategy = choose_strategy(strategy_of(experiment, member), case, config.gap)
    except StrategyError as err:
        raise UsageError(f"--strategy: {err}") from None
    with Bus(args.run_id, args.id, bus_config(args, "client", args.id),
             faults=message_faults(args, args.run_id, args.id, experiment)) as bus:
        MicrogridAgent(bus, case, config, experiment.market_day, strategy).run()
    return 0
