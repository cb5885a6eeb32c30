"""``dmosim router``: a standalone Zenoh router; the DMO and agents then connect to it as clients, and routers on
several hosts connect to one another into a mesh (docs/hosts.md)."""

from __future__ import annotations

import argparse
import logging
import queue

import zenoh

from messages.keys import Keys

from ..arguments import agents
from ..console import UsageError
from .flags import (DEFAULT_AGENTS, add_bus_flags, agent_ids, announce_run_id, bus_config, check_bus_flags,
                    credentials_for, run_id_of, setup_logging)

HELP = "a standalone Zenoh router for the DMO and agents to connect to, and for other routers (a mesh of hosts)"
log = logging.getLogger("dmosim")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--run-id", help="the run this router serves (default: a new one, printed; a router that "
                                    "--connect's to others needs theirs)")
    p.add_argument("--agents", type=agents, help="agents mg1..mgN the credentials are made for, without --auth-dir "
                                                 f"(default: {DEFAULT_AGENTS})")
    p.add_argument("--fleet", help="fleet TOML file naming the agents instead of --agents")
    p.add_argument("--quiet", action="store_true", help="log warnings only")
    add_bus_flags(p, "router")


def check_relay_flags(args) -> None:
    """A router that connects to other routers joins their run: it needs that run's id, and it makes no credentials,
    so it names no agents to make them for."""
    if not args.connect:
        return
    if args.agents is not None or args.fleet is not None:
        raise UsageError(f"{'--agents' if args.agents is not None else '--fleet'}: a router that connects to other "
                         "routers makes no credentials; it uses the run's (--auth-dir DIR --user NAME, docs/hosts.md)")
    if args.run_id is None:
        raise UsageError("--connect: a router that connects to other routers joins their run; give its --run-id")


def run(args) -> int:
    setup_logging("router", args.quiet)
    if args.agents is not None and args.fleet is not None:
        raise UsageError("--agents and --fleet exclude each other: a fleet file names its agents")
    check_bus_flags(args, "router")
    check_relay_flags(args)
    names = agent_ids(args.fleet, args.agents or DEFAULT_AGENTS)
    run_id = run_id_of(args)
    credentials_for(args, run_id, names, dmo_client=True)  # a router that connects makes none: it checks its flags
    config = bus_config(args, "router", run_id=run_id)
    announce_run_id(args)
    events: queue.Queue = queue.Queue()
    with zenoh.open(config.to_zenoh()) as session:
        log.info("router %s listening on %s%s", session.info.zid(), ", ".join(config.listen) or "zenoh's default "
                 "endpoints", f"; connecting to {', '.join(config.connect)}" if config.connect else "")
        with session.info.declare_transport_events_listener(events.put, history=True):
            try:
                hold_links(session, Keys(run_id), events)
            except KeyboardInterrupt:
                pass
    return 0


def hold_links(session: zenoh.Session, keys: Keys, events: queue.Queue) -> None:
    """For as long as the router runs, hold a liveliness token for each link it has to another router of the mesh
    (``Keys.link``; clients come and go unsaid), and log each as it comes up and goes down. Whoever may see the
    run's keys sees the mesh's links by them: ``dmosim run --routers N`` waits for them before it starts the DMO
    (dmosim/launch/mesh.py). The tokens are declared here, not in Zenoh's callback, which must not block."""
    zid, tokens = str(session.info.zid()), {}
    while True:
        event = events.get()
        if event.transport.whatami != zenoh.WhatAmI.ROUTER:
            continue
        peer, up = str(event.transport.zid), event.kind == zenoh.SampleKind.PUT
        log.info("router link %s: router %s", "up" if up else "down", peer)
        if up and peer not in tokens:
            tokens[peer] = session.liveliness().declare_token(keys.link(zid, peer))
        elif not up and peer in tokens:
            tokens.pop(peer).undeclare()
