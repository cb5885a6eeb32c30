"""The ``--cluster`` flags that ``dmosim run`` and ``dmosim sweep`` share (docs/cluster.md): their help, their values
checked before anything starts (a scheduler reached without dmosim's TLS certificates is refused unless the user
says ``--insecure-cluster``), and the cluster they name connected, or the one line that says why not (bad input
exits 2; a scheduler that does not answer or refuses the connection is a runtime failure, exit 1)."""

from __future__ import annotations

import argparse
from pathlib import Path

from messages.transport.access import AuthError

from ..console import UsageError
from ..launch.cluster import INSTALL, Cluster, ClusterUsage, connect, scheduler_address
from ..launch.clusterauth import CREDENTIALS_COMMAND, client_security


def add_cluster_flag(p: argparse.ArgumentParser, what: str) -> None:
    """``--cluster ADDRESS``, ``--cluster-auth DIR`` and ``--insecure-cluster``: ``what`` says what goes on the
    cluster's workers."""
    p.add_argument("--cluster", metavar="ADDRESS",
                   help=f"run {what} on the workers of a Dask cluster: its scheduler, tls://HOST:PORT, or the file of "
                        f"dask scheduler --scheduler-file; --out must be on a filesystem the workers share "
                        f"(docs/cluster.md; needs {INSTALL})")
    p.add_argument("--cluster-auth", metavar="DIR",
                   help=f"with --cluster: the cluster's TLS credentials ({CREDENTIALS_COMMAND}), whose bundle "
                        "DIR/client/ this launcher connects with; the scheduler and workers run with theirs")
    p.add_argument("--insecure-cluster", action="store_true",
                   help="with --cluster: use a scheduler without TLS (tcp://HOST:PORT), which lets anyone who "
                        "reaches it run any code on its workers (a network only you use)")


def check_cluster(args) -> None:
    """The ``--cluster`` flags as given, Dask installed, and the scheduler reached over mutual TLS with dmosim's
    certificates unless ``--insecure-cluster``, or the one-line ``UsageError``; nothing is reached."""
    if args.cluster is None:
        for flag, given in (("--cluster-auth", args.cluster_auth), ("--insecure-cluster", args.insecure_cluster)):
            if given:
                raise UsageError(f"{flag} goes with --cluster")
        return
    try:
        import distributed  # noqa: F401, PLC0415  (an extra; imported only with --cluster)
    except ImportError:
        raise UsageError(f"--cluster needs Dask distributed, which is not installed: {INSTALL}") from None
    try:
        scheme, _, _ = scheduler_address(args.cluster)
    except ClusterUsage as exc:
        raise UsageError(str(exc)) from None
    if args.cluster_auth and args.insecure_cluster:
        raise UsageError("--cluster-auth and --insecure-cluster exclude each other: choose TLS or an open scheduler")
    if args.insecure_cluster and scheme == "tls":
        raise UsageError(f"--cluster {args.cluster}: a tls:// scheduler is reached with --cluster-auth DIR, the "
                         f"cluster's credentials ({CREDENTIALS_COMMAND}), not --insecure-cluster")
    if args.insecure_cluster:
        return
    if not args.cluster_auth:
        raise UsageError(f"--cluster {args.cluster}: a Dask scheduler's users can run any code on its workers; reach "
                         f"it over TLS with --cluster-auth DIR ({CREDENTIALS_COMMAND}), or pass --insecure-cluster on "
                         "a network only you use (docs/cluster.md)")
    if scheme != "tls":
        raise UsageError(f"--cluster {args.cluster}: with --cluster-auth the scheduler is reached at tls://HOST:PORT, "
                         "started with the cluster's certificates (docs/cluster.md)")
    security(args)


def security(args):
    """The ``distributed.Security`` of ``--cluster-auth``, or None without it; the one-line ``UsageError`` for
    credentials that cannot be used."""
    if not args.cluster_auth:
        return None
    try:
        return client_security(args.cluster_auth)
    except AuthError as exc:
        raise UsageError(f"--cluster-auth {exc}") from None


def connected(args, advertise: str | None = None) -> Cluster:
    """The cluster of ``--cluster``, connected (``ClusterError``, a runtime failure, if it does not answer)."""
    try:
        return connect(args.cluster, advertise, security=security(args))
    except ClusterUsage as exc:
        raise UsageError(str(exc)) from None


def check_shared(cluster: Cluster, directory: Path) -> None:
    """The one-line ``UsageError`` unless every worker sees ``directory``."""
    try:
        cluster.check_sees(directory)
    except ClusterUsage as exc:
        raise UsageError(f"--out {exc}") from None
