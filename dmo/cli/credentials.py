"""``dmosim credentials``: per-run passwords, access-control rules and TLS certificates for roles on several hosts."""

from __future__ import annotations

import argparse
from pathlib import Path

from messages.transport.access import READERS, AuthError
from messages.transport.credentials import DEFAULT_HOSTS, create_auth_dir
from scenarios.fleet import FleetError, load_fleet, make_fleet

from .console import UsageError
from .flags import positive_int

HELP = "passwords, access-control rules and TLS certificates of one run, for roles on several hosts (docs/security.md)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="DIR", help="directory to create: the router's files, and "
                                                               "one bundle DIR/<name>/ per other process")
    p.add_argument("--run-id", default="day", help="the run the rules are for (default: day)")
    p.add_argument("--agents", type=positive_int, default=3, help="agents mg1..mgN (default: 3)")
    p.add_argument("--fleet", help="fleet TOML file naming the agents (overrides --agents)")
    p.add_argument("--reader", action="append", default=[], metavar="NAME",
                   help="a process that may hear everything of the run and publish nothing (repeatable; "
                        "default: recorder)")
    p.add_argument("--tls", action="store_true",
                   help="also make a CA and certificates: every process must then connect over tls/ endpoints "
                        "with its own certificate")
    p.add_argument("--host", action="append", default=[], metavar="NAME",
                   help="host name or IP address the router's certificate is valid for (repeatable; default: "
                        "localhost and 127.0.0.1)")
    p.add_argument("--days", type=positive_int, default=30, help="validity of the certificates (default: 30)")
    p.add_argument("--overwrite", action="store_true", help="replace what DIR holds")


def run(args) -> int:
    try:
        fleet = load_fleet(args.fleet) if args.fleet else make_fleet(args.agents)
        out = create_auth_dir(args.out, args.run_id, [m.id for m in fleet], readers=tuple(args.reader) or READERS,
                              tls=args.tls, hosts=tuple(args.host) or DEFAULT_HOSTS, valid_days=args.days,
                              overwrite=args.overwrite)
    except (FleetError, AuthError) as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    bundles = sorted(p.name for p in Path(out).iterdir() if p.is_dir())
    print(f"credentials for run {args.run_id} in {out}{' (with TLS certificates)' if args.tls else ''}")
    print(f"  DMO host (the router): dmosim dmo --run-id {args.run_id} --auth-dir {out} --listen "
          f"{'tls' if args.tls else 'tcp'}/HOST:7447 ...")
    print(f"  each other host gets only its bundle, {out}/<name>/ (copy it to DIR/<name>/ there, and keep it "
          f"private): dmosim agent --id <name> --auth-dir DIR ...")
    print(f"  bundles: {', '.join(bundles)}")
    return 0
