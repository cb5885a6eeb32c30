"""``dmosim router``: a standalone Zenoh router; the DMO and agents then connect to it as clients."""

from __future__ import annotations

import argparse
import logging
import threading

import zenoh

from ..arguments import agents
from ..console import UsageError
from .flags import (DEFAULT_AGENTS, add_bus_flags, agent_ids, announce_run_id, bus_config, check_bus_flags,
                    credentials_for, run_id_of, setup_logging)

HELP = "a standalone Zenoh router for the DMO and agents to connect to"
log = logging.getLogger("dmosim")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run-id", help="the run this router serves (default: a new one, printed)")
    p.add_argument("--agents", type=agents, help="agents mg1..mgN the credentials are made for, without --auth-dir "
                                                 f"(default: {DEFAULT_AGENTS})")
    p.add_argument("--fleet", help="fleet TOML file naming the agents instead of --agents")
    p.add_argument("--quiet", action="store_true", help="log warnings only")
    add_bus_flags(p, "router")


def run(args) -> int:
    setup_logging("router", args.quiet)
    if args.agents is not None and args.fleet is not None:
        raise UsageError("--agents and --fleet exclude each other: a fleet file names its agents")
    check_bus_flags(args, "router")
    names = agent_ids(args.fleet, args.agents or DEFAULT_AGENTS)
    run_id = run_id_of(args)
    credentials_for(args, run_id, names, dmo_client=True)
    config = bus_config(args, "router", run_id=run_id)
    announce_run_id(args)
    stop = threading.Event()
    with zenoh.open(config.to_zenoh()):
        log.info("router listening on %s", ", ".join(config.listen) or "zenoh's default endpoints")
        try:
            stop.wait()
        except KeyboardInterrupt:
            pass
    return 0
