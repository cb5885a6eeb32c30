"""``dmosim router``: a standalone Zenoh router; the DMO and agents then connect to it as clients."""

from __future__ import annotations

import argparse
import logging
import threading

import zenoh

from .flags import add_bus_flags, bus_config, setup_logging

HELP = "a standalone Zenoh router for the DMO and agents to connect to"
log = logging.getLogger("dmosim")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true")
    add_bus_flags(p)


def run(args) -> int:
    setup_logging("router", args.quiet)
    config = bus_config(args, "router")
    stop = threading.Event()
    with zenoh.open(config.to_zenoh()):
        log.info("router listening on %s", ", ".join(config.listen) or "zenoh's default endpoints")
        try:
            stop.wait()
        except KeyboardInterrupt:
            pass
    return 0
