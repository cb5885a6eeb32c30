"""``dmosim credentials``: per-run passwords, access-control rules and TLS certificates for roles on several hosts."""

from __future__ import annotations

from pathlib import Path

from messages.security import DEFAULT_HOSTS, READERS, AuthError, create_auth_dir
from scenarios.fleet import FleetError, load_fleet, make_fleet

from ..console import UsageError


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
