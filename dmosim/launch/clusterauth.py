"""The TLS credentials of a Dask cluster for ``--cluster`` (docs/cluster.md): made (a CA of their own, and the
scheduler's, the workers' and the launcher's certificates, by the helper that makes a run's) and read back as a
``distributed.Security`` (the launcher's, or every role's for a Python that starts the cluster itself), which
refuses any connection that is not mutual TLS with that CA.

The layout, one bundle per role, each as a run's (messages/transport/access.py)::

    DIR/scheduler/ca.pem cert.pem key.pem    the scheduler's (it serves, and connects to the workers)
    DIR/worker/ca.pem cert.pem key.pem       every worker's, one for all (they serve, and connect)
    DIR/client/ca.pem cert.pem key.pem       the launcher's: dmosim run or sweep --cluster-auth DIR

Dask checks that a peer's certificate is signed by the CA, not whose it is (no host names): whoever holds any of
the three keys is a user of the cluster, who may run any code on its workers.
"""

from __future__ import annotations

import datetime as dt
import os
import ssl
from pathlib import Path

from messages.transport.access import CA_FILE, CERT_FILE, KEY_FILE, AuthError
from messages.transport.credentials import Leaf, check_private, check_validity, fresh_directory, write_certificates

SCHEDULER, WORKER, CLIENT = "scheduler", "worker", "client"  # the bundles, each named for its role in Dask
CREDENTIALS_COMMAND = "dmosim credentials --cluster --out DIR"  # what makes them


def create_cluster_auth(out: str | os.PathLike, valid_days: int, *, overwrite: bool = False) -> Path:
    """Fresh credentials of a cluster in ``out`` (made private; ``overwrite`` replaces what it holds): a new CA and
    a certificate for each role, valid for ``valid_days``."""
    out = Path(out)
    check_validity(valid_days)  # before anything is made
    fresh_directory(out, overwrite)
    for role in (SCHEDULER, WORKER, CLIENT):
        (out / role).mkdir(mode=0o700)
    write_certificates([Leaf(out / SCHEDULER, "dask scheduler", server=True, client=True),
                        Leaf(out / WORKER, "dask worker", server=True, client=True),
                        Leaf(out / CLIENT, "dmosim launcher", client=True)], valid_days, authority="dmosim cluster CA")
    return out


def client_security(directory: str | os.PathLike):
    """The launcher's ``distributed.Security`` from the bundle ``DIR/client/`` of ``directory``: mutual TLS with the
    cluster's CA, nothing unencrypted. ``AuthError`` (one line) for a bundle that is missing, not private
    (``check_private``), unreadable as certificates, or expired."""
    return _security(Path(directory), (CLIENT,))


def cluster_security(directory: str | os.PathLike):
    """The ``distributed.Security`` of a Python process that starts the cluster itself (a ``LocalCluster``,
    dask-jobqueue's ``SLURMCluster``, docs/cluster.md): every role's bundle of ``directory``, checked as
    ``client_security`` checks the launcher's."""
    return _security(Path(directory), (SCHEDULER, WORKER, CLIENT))


def _security(directory: Path, roles: tuple[str, ...]):
    from distributed import Security  # noqa: PLC0415  (an extra: only --cluster needs it)

    if not directory.is_dir():
        raise AuthError(f"{directory}: no such directory (make the cluster's credentials with {CREDENTIALS_COMMAND})")
    check_private(directory)
    for role in roles:
        missing = [name for name in (CA_FILE, CERT_FILE, KEY_FILE) if not (directory / role / name).is_file()]
        if missing:
            raise AuthError(f"{directory / role}: holds no {missing[0]}; expected the bundle {role}/ that "
                            f"{CREDENTIALS_COMMAND} makes")
    security = Security(require_encryption=True, tls_ca_file=str(directory / roles[0] / CA_FILE),
                        **{f"tls_{role}_{kind}": str(directory / role / name) for role in roles
                           for kind, name in (("cert", CERT_FILE), ("key", KEY_FILE))})
    for role in roles:
        try:  # loads the files: a wrong one is told here, not by a failed handshake
            security.get_connection_args(role)
        except (ssl.SSLError, OSError) as exc:
            raise AuthError(f"{directory / role}: not a certificate and key of the cluster's: "
                            f"{exc.strerror or exc}") from None
        _check_valid(directory / role / CERT_FILE)
    return security


def _check_valid(path: Path) -> None:
    """``AuthError`` unless the certificate at ``path`` is valid now."""
    from cryptography import x509  # noqa: PLC0415

    cert = x509.load_pem_x509_certificate(path.read_bytes())
    now = dt.datetime.now(dt.timezone.utc)
    if not cert.not_valid_before_utc <= now <= cert.not_valid_after_utc:
        raise AuthError(f"{path}: valid from {cert.not_valid_before_utc:%Y-%m-%d %H:%M} to "
                        f"{cert.not_valid_after_utc:%Y-%m-%d %H:%M} UTC, not now; make new credentials "
                        f"({CREDENTIALS_COMMAND}) and restart the scheduler and workers with them")
