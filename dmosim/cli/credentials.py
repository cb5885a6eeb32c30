"""``dmosim credentials``: per-run passwords, access-control rules and TLS certificates for roles on several hosts;
with ``--cluster``, the TLS certificates of a Dask cluster for ``--cluster-auth`` instead (docs/cluster.md)."""

from __future__ import annotations

import argparse
from pathlib import Path

from messages.transport.access import CA_FILE, CERT_FILE, KEY_FILE, READERS, AuthError
from messages.transport.credentials import DEFAULT_HOSTS, MAX_CERT_DAYS, MAX_HOSTS, MAX_READERS, create_auth_dir
from scenarios.fleet import FleetError, load_fleet, make_fleet

from ..arguments import agents, integer
from ..console import UsageError
from ..launch.clusterauth import CLIENT, SCHEDULER, WORKER, create_cluster_auth
from .flags import DEFAULT_AGENTS, run_id_of

HELP = ("passwords, access-control rules and TLS certificates of one run, for roles on several hosts "
        "(docs/security.md); --cluster: a Dask cluster's TLS certificates (docs/cluster.md)")
RUN_FLAGS = ("run_id", "agents", "fleet", "reader", "router", "tls", "host")  # what --cluster's certificates ignore


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="DIR", help="directory to create: the router's files, and "
                                                               "one bundle DIR/<name>/ per other process")
    p.add_argument("--cluster", action="store_true",
                   help="instead of a run's credentials, a Dask cluster's: a CA and the bundles DIR/scheduler/, "
                        "DIR/worker/ (one for every worker) and DIR/client/ (dmosim run and sweep --cluster-auth DIR); "
                        "takes --days and --overwrite only (docs/cluster.md)")
    p.add_argument("--run-id", help="the run the rules are for (default: a new one, printed)")
    p.add_argument("--agents", type=agents, help=f"agents mg1..mgN (default: {DEFAULT_AGENTS})")
    p.add_argument("--fleet", help="fleet TOML file naming the agents instead of --agents")
    p.add_argument("--reader", action="append", default=[], metavar="NAME",
                   help="a process that may hear everything of the run and publish nothing (repeatable, at most "
                        f"{MAX_READERS}; default: recorder)")
    p.add_argument("--router", action="append", default=[], metavar="NAME",
                   help="a router of a mesh that connects to other routers, one per host (repeatable, at most "
                        f"{MAX_HOSTS}; needs --tls; docs/hosts.md)")
    p.add_argument("--tls", action="store_true",
                   help="also make a CA and certificates: every process must then connect over tls/ endpoints "
                        "with its own certificate")
    p.add_argument("--host", action="append", default=[], metavar="NAME",
                   help="host name or IP address the router's certificate is valid for (repeatable, at most "
                        f"{MAX_HOSTS}; default: localhost and 127.0.0.1)")
    p.add_argument("--days", type=integer(1, MAX_CERT_DAYS), default=30,
                   help=f"validity of the certificates, at most {MAX_CERT_DAYS} days (default: 30)")
    p.add_argument("--overwrite", action="store_true", help="replace what DIR holds")


def run(args) -> int:
    if args.cluster:
        return _cluster(args)
    if args.agents is not None and args.fleet is not None:
        raise UsageError("--agents and --fleet exclude each other: a fleet file names its agents")
    try:
        fleet = load_fleet(args.fleet) if args.fleet else make_fleet(args.agents or DEFAULT_AGENTS)
        run_id = run_id_of(args)
        out = create_auth_dir(args.out, run_id, [m.id for m in fleet], readers=tuple(args.reader) or READERS,
                              tls=args.tls, hosts=tuple(args.host) or DEFAULT_HOSTS, valid_days=args.days,
                              routers=tuple(args.router), overwrite=args.overwrite)
    except (FleetError, AuthError) as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot write {args.out}: {exc.strerror or exc}") from None
    bundles = sorted(p.name for p in Path(out).iterdir() if p.is_dir())
    print(f"credentials for run {run_id} in {out}{' (with TLS certificates)' if args.tls else ''}")
    print(f"  DMO host (the router): dmosim dmo --run-id {run_id} --auth-dir {out} --listen "
          f"{'tls' if args.tls else 'tcp'}/HOST:7447 ...")
    print(f"  each other host gets only its bundle, {out}/<name>/ (copy it to DIR/<name>/ there, and keep it "
          f"private): dmosim agent --id <name> --run-id {run_id} --auth-dir DIR ...")
    for router in args.router:
        print(f"  {router}'s host (a router of the mesh): dmosim router --run-id {run_id} --auth-dir DIR --user "
              f"{router} --listen tls/HOST:7447 --connect tls/DMO-HOST:7447, DIR holding {out}'s router files "
              f"and its bundle {out}/{router}/ (docs/hosts.md)")
    print(f"  bundles: {', '.join(bundles)}")
    return 0


def _cluster(args) -> int:
    """``--cluster``: the cluster's certificates, and the commands that use them."""
    given = [name for name in RUN_FLAGS if getattr(args, name) not in (None, False, [])]
    if given:
        raise UsageError(f"--{given[0].replace('_', '-')} is for a run's credentials; --cluster makes a Dask "
                         "cluster's, which take --days and --overwrite only")
    try:
        out = create_cluster_auth(args.out, args.days, overwrite=args.overwrite)
    except AuthError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot write {args.out}: {exc.strerror or exc}") from None

    def tls(role: str) -> str:
        bundle = out / role
        return f"--tls-ca-file {bundle / CA_FILE} --tls-cert {bundle / CERT_FILE} --tls-key {bundle / KEY_FILE}"

    print(f"TLS credentials of a Dask cluster in {out}, valid for {args.days} days: a CA of their own and the bundles "
          f"{SCHEDULER}/, {WORKER}/ and {CLIENT}/; give each host only its bundle, and keep it private "
          "(docs/cluster.md)")
    print(f"  scheduler host: dask scheduler --host PRIVATE-IP --port 8786 --dashboard-address 127.0.0.1:8787 "
          f"{tls(SCHEDULER)}")
    print(f"  each worker host: dask worker tls://PRIVATE-IP:8786 --host WORKER-IP --dashboard-address 127.0.0.1:0 "
          f"--nthreads 1 {tls(WORKER)}")
    print(f"  this machine: dmosim run ... --cluster tls://PRIVATE-IP:8786 --cluster-auth {out}")
    return 0
