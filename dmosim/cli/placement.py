"""The ``--cluster`` flag that ``dmosim run`` and ``dmosim sweep`` share (docs/cluster.md): its help, its value
checked before anything starts, and the cluster it names connected, or the one line that says why not (bad input
exits 2; a scheduler that does not answer is a runtime failure, exit 1)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..console import UsageError
from ..launch.cluster import INSTALL, Cluster, ClusterUsage, connect, scheduler_address


def add_cluster_flag(p: argparse.ArgumentParser, what: str) -> None:
    """``--cluster ADDRESS``: ``what`` says what goes on the cluster's workers."""
    p.add_argument("--cluster", metavar="ADDRESS",
                   help=f"run {what} on the workers of a Dask cluster: its scheduler, tcp://HOST:PORT, or the file of "
                        f"dask scheduler --scheduler-file; --out must be on a filesystem the workers share "
                        f"(docs/cluster.md; needs {INSTALL})")


def check_cluster(args) -> None:
    """``--cluster``'s value well formed and Dask installed, or the one-line ``UsageError``; nothing is reached."""
    if args.cluster is None:
        return
    try:
        import distributed  # noqa: F401, PLC0415  (an extra; imported only with --cluster)
    except ImportError:
        raise UsageError(f"--cluster needs Dask distributed, which is not installed: {INSTALL}") from None
    try:
        scheduler_address(args.cluster)
    except ClusterUsage as exc:
        raise UsageError(str(exc)) from None


def connected(args, advertise: str | None = None) -> Cluster:
    """The cluster of ``--cluster``, connected (``ClusterError``, a runtime failure, if it does not answer)."""
    try:
        return connect(args.cluster, advertise)
    except ClusterUsage as exc:
        raise UsageError(str(exc)) from None


def check_shared(cluster: Cluster, directory: Path) -> None:
    """The one-line ``UsageError`` unless every worker sees ``directory``."""
    try:
        cluster.check_sees(directory)
    except ClusterUsage as exc:
        raise UsageError(f"--out {exc}") from None
