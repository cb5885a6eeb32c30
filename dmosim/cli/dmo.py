"""``dmosim dmo``: the market operator role alone, for days spread over several hosts (the Zenoh router by default)."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import threading
from pathlib import Path

from dmo.operator.config import DayConfig
from messages.budget import BUDGET_BYTES, BUDGET_MESSAGES
from messages.transport import Bus

from ..arguments import budget, wait
from ..console import UsageError
from ..experiment.spec import Experiment
from ..launch.roles import day_config, fleet_of
from ..results.report import result_text
from .flags import (add_bus_flags, add_fault_flags, announce_run_id, bus_config, check_bus_flags, check_fault_flags,
                    credentials_for, message_faults, run_id_of, setup_logging)
from .settings import DMO_SETTINGS, add_experiment_flag, role_experiment

HELP = "the market operator role alone (the Zenoh router by default)"
log = logging.getLogger("dmosim")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run-id", help="key prefix shared with the agents (default: a new one, printed)")
    add_experiment_flag(p, DMO_SETTINGS)
    p.add_argument("--result", help="write the day's JSON result here (default: stdout)")
    p.add_argument("--journal", metavar="PATH",
                   help="journal the day here; a DMO restarted with the same journal, run id and market day "
                        "resumes the day from it (docs/faults.md)")
    p.add_argument("--await-recorder", type=wait, default=0.0, metavar="S",
                   help="wait up to S seconds for a recorder of this run before the first message (default: 0, "
                        "do not wait)")
    p.add_argument("--budget", type=budget, default=(BUDGET_MESSAGES, BUDGET_BYTES), metavar="MESSAGES,BYTES",
                   help="what one agent may send in a phase or real-time hour before what it sends more is dropped "
                        f"unread (default: {BUDGET_MESSAGES},{BUDGET_BYTES}; docs/protocol.md, \"Budgets\")")
    p.add_argument("--quiet", action="store_true", help="log warnings only")
    add_fault_flags(p)
    add_bus_flags(p, "router")


def day_config_of(experiment: Experiment, journal: str | None) -> DayConfig:
    """The DMO's days; a settlement rule that cannot be loaded or disagrees with the market is a UsageError."""
    try:
        return day_config(experiment, journal=journal)
    except ValueError as exc:
        where = "--settlement" if experiment.market.settlement else "the experiment"
        raise UsageError(f"{where}: {exc}") from None


def run(args) -> int:
    setup_logging("dmo", args.quiet)
    check_fault_flags(args)
    check_bus_flags(args, "router")
    experiment = role_experiment(args)
    names = [m.id for m in fleet_of(experiment)]
    config = dataclasses.replace(day_config_of(experiment, args.journal), budget=args.budget)
    run_id = run_id_of(args)
    credentials_for(args, run_id, names, dmo_client=False)
    settings = bus_config(args, "router", "dmo", run_id)
    announce_run_id(args)
    progress = lambda phase, hour: log.info("phase %s%s", phase, f" hour {hour}/24" if hour else "")  # noqa: E731
    with Bus(run_id, "dmo", settings, faults=message_faults(args, run_id, "dmo", experiment)) as bus:
        before_start = (lambda: await_recorder(bus, args.await_recorder)) if args.await_recorder else None
        from dmo.operator.day import MarketDay  # noqa: PLC0415  (its clearing on a feeder loads scipy's LP)

        result = MarketDay(bus, config, progress).run(before_start)
        transport = bus.stats() | ({"faults_injected": bus.faults_injected()} if bus.faults else {})
    text = result_text(result.report(run_id, transport))
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
