"""``dmosim router``: a standalone Zenoh router; the DMO and agents then connect to it as clients."""

from __future__ import annotations

import argparse
import logging
import threading

import zenoh

from .flags import add_bus_flags, agent_ids, bus_config, credentials_for, positive_int, setup_logging

HELP = "a standalone Zenoh router for the DMO and agents to connect to"
log = logging.getLogger("dmosim")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run-id", default="day", help="the run this router serves (default: day)")
    p.add_argument("--agents", type=positive_int, default=3, help="agents mg1..mgN the credentials are made for, "
                                                                    "without --auth-dir (default: 3)")
    p.add_argument("--fleet", help="fleet TOML file naming the agents instead")
    p.add_argument("--quiet", action="store_true")
    add_bus_flags(p)


def run(args) -> int:
    setup_logging("router", args.quiet)
    credentials_for(args, args.run_id, agent_ids(args.fleet, args.agents), dmo_client=True)
    config = bus_config(args, "router", run_id=args.run_id)
    stop = threading.Event()
    with zenoh.open(config.to_zenoh()):
        log.info("router listening on %s", ", ".join(config.listen) or "zenoh's default endpoints")
        try:
            stop.wait()
        except KeyboardInterrupt:
            pass
    return 0
