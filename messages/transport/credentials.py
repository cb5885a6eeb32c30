"""Make the credentials of one run: a password per process, the router's user dictionary and access-control file
(access.py), and with TLS a CA, the router's certificate and one client certificate per process; carry one
process's bundle to the host that runs it; and check that credentials found on disk are private to this user before
any process uses them. ``write_certificates`` is the one maker of certificates (a Dask cluster's too,
dmosim/launch/clusterauth.py).

The layout of the directory is in access.py, which reads it back; every secret is created readable by its owner
only, every other file and directory writable by its owner only.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import secrets
import shutil
import stat
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from scenarios.names import DMO

from ..keys import Keys
from .access import (ACL_FILE, CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE, READERS, ROUTER_CERT_NAME, USERS_FILE,
                     AuthError, access_control)

DEFAULT_HOSTS = ("localhost", "127.0.0.1")  # what the router's certificate is valid for, unless told
SECRETS = (USERS_FILE, PASSWORD_FILE, KEY_FILE)  # files that hold a secret, wherever they are in a directory
BUNDLE_FILES = (PASSWORD_FILE, CA_FILE, CERT_FILE, KEY_FILE)  # what a client's bundle holds (the last three: TLS)
# Certificates cannot be revoked (docs/security.md): a year is their longest validity, far longer than a run.
MAX_CERT_DAYS = 366
MAX_READERS = 16  # readers of one run (the recorder, taps): each may hear everything
MAX_HOSTS = 16    # names and addresses the router's certificate is valid for; and routers of a mesh, one per host


def create_auth_dir(out: str | os.PathLike, run_id: str, agents: Sequence[str], *, readers: Sequence[str] = READERS,
                    tls: bool = False, hosts: Sequence[str] = DEFAULT_HOSTS, valid_days: int = 30,
                    dmo_client: bool = True, routers: Sequence[str] = (), overwrite: bool = False) -> Path:
    """Generate fresh credentials for one run: a random password per process, the router's dictionary and rules,
    and with ``tls`` a new CA with a certificate for the router (valid for ``hosts``) and one per process.
    Without ``dmo_client`` there are no credentials for the DMO: it must be the router itself. ``routers`` are the
    other routers of a mesh (docs/hosts.md), each with a bundle to log in to the routers it connects to; they need
    ``tls``, and serve with the same router files."""
    out = Path(out)
    if len(readers) > MAX_READERS or len(hosts) > MAX_HOSTS or len(routers) > MAX_HOSTS:
        raise AuthError(f"at most {MAX_READERS} readers, {MAX_HOSTS} host names and {MAX_HOSTS} routers, not "
                        f"{len(readers)}, {len(hosts)} and {len(routers)}")
    check_validity(valid_days)
    if tls and not hosts:
        raise AuthError("TLS needs at least one host name or address for the router's certificate")
    Keys(run_id)  # a bad run id fails here, not in the router
    acl = access_control(run_id, agents, readers, tls=tls, dmo_client=dmo_client, routers=routers)  # checks names
    fresh_directory(out, overwrite)
    names = [*([DMO] if dmo_client else []), *readers, *routers, *agents]
    passwords = {name: secrets.token_urlsafe(24) for name in names}
    for name in names:
        (out / name).mkdir(mode=0o700)
    _write(out / USERS_FILE, "".join(f"{n}:{p}\n" for n, p in passwords.items()))
    _write(out / ACL_FILE, json.dumps(acl, indent=2) + "\n", public=True)
    for name, password in passwords.items():
        _write(out / name / PASSWORD_FILE, password)  # the password alone: what a client sends is the file
    if tls:
        # the router's server certificate (common name ROUTER_CERT_NAME, which no client certificate has) and one
        # client certificate per process, whose common name the access-control subjects match
        write_certificates([Leaf(out, ROUTER_CERT_NAME, server=True, hosts=tuple(hosts)),
                            *(Leaf(out / n, n, client=True) for n in names)], valid_days)
    return out


def check_validity(valid_days: int) -> None:
    """``AuthError`` unless certificates may be made valid for ``valid_days``."""
    if not 1 <= valid_days <= MAX_CERT_DAYS:
        raise AuthError(f"certificates are valid for 1..{MAX_CERT_DAYS} days, not {valid_days}")


def fresh_directory(out: Path, overwrite: bool) -> None:
    """``out`` made (or emptied, with ``overwrite``) as a directory of credentials: this user's, mode 0700, empty;
    ``AuthError`` for another user's directory, a file, or one that holds something without ``overwrite``."""
    if out.exists():
        if not out.is_dir():
            raise AuthError(f"{out} exists and is not a directory")
        _check_owner(out)  # another user's directory could be filled behind our back
        out.chmod(0o700)   # before looking inside: nobody else may add anything from now on
        if any(out.iterdir()):
            if not overwrite:
                raise AuthError(f"{out} is not empty; remove it or choose another directory")
            shutil.rmtree(out)
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    out.chmod(0o700)


def read_bundle(auth: str | os.PathLike, name: str) -> dict[str, str]:
    """The files of process ``name``'s bundle in ``auth``, by file name: all it needs to log in, for
    ``write_bundle`` to put elsewhere (on the host that runs it, and nothing of the others')."""
    bundle = Path(auth) / name
    return {file: (bundle / file).read_text() for file in BUNDLE_FILES if (bundle / file).is_file()}


def write_bundle(auth: str | os.PathLike, name: str, files: Mapping[str, str]) -> Path:
    """``files`` (as ``read_bundle`` gives them) as process ``name``'s bundle in ``auth``, a private directory
    that then serves as its ``--auth-dir``; each file made as ``create_auth_dir`` makes it."""
    unknown = sorted(set(files) - set(BUNDLE_FILES))
    if unknown:
        raise AuthError(f"{unknown[0]} is not a file of a bundle ({', '.join(BUNDLE_FILES)})")
    bundle = Path(auth) / name
    bundle.mkdir(mode=0o700)
    for file, text in files.items():
        _write(bundle / file, text, public=file not in SECRETS)
    return bundle


def private_directory(path: str | os.PathLike) -> Path:
    """``path`` as a directory only this user can change: made (mode 0700) if missing, else checked as
    ``check_private`` checks a directory (its contents aside)."""
    path = Path(path)
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    _check(path, path.stat(), secret=False)
    return path


def check_private(path: str | os.PathLike, *, secret: bool = False) -> None:
    """Refuse, with an AuthError naming the path and what is wrong, credentials that someone else could have made
    or changed, as ssh refuses such keys: a directory of credentials, each entry in it and in each bundle
    directory in it must be owned by this user and writable by nobody else, and a secret (users.txt, password,
    key.pem, or the file itself with ``secret``) readable by nobody else. A path that does not exist is left to
    whoever reads it to report."""
    path = Path(path)
    try:
        top = path.stat()
    except FileNotFoundError:
        return
    except OSError as exc:
        raise AuthError(f"cannot read {path}: {exc.strerror or exc}") from None
    _check(path, top, secret=secret or path.name in SECRETS)
    if not stat.S_ISDIR(top.st_mode):
        return
    for entry in _entries(path):  # the directory's files and bundles, and each bundle's files: no deeper
        info = entry.stat()
        _check(entry, info, secret=entry.name in SECRETS)
        if stat.S_ISDIR(info.st_mode):
            for inner in _entries(entry):
                _check(inner, inner.stat(), secret=inner.name in SECRETS)


def _entries(directory: Path) -> list[Path]:
    try:
        return sorted(directory.iterdir())
    except OSError as exc:
        raise AuthError(f"cannot read {directory}: {exc.strerror or exc}") from None


def _check(path: Path, info: os.stat_result, *, secret: bool) -> None:
    _check_owner(path, info)
    mode = stat.S_IMODE(info.st_mode)
    if mode & 0o022:
        raise AuthError(f"{path} is writable by {'its group' if mode & 0o020 else 'everyone'} (mode {mode:04o}): "
                        f"credentials anyone else could change are not used; chmod go-w {path}, or make new ones")
    if secret and mode & 0o077:
        raise AuthError(f"{path} is readable by others (mode {mode:04o}): a secret must be its owner's alone; "
                        f"chmod 600 {path}, or make new credentials")


def _check_owner(path: Path, info: os.stat_result | None = None) -> None:
    owner = (info or path.stat()).st_uid
    if owner != os.getuid():
        raise AuthError(f"{path} is owned by user {owner}, not by this user ({os.getuid()}): credentials someone "
                        "else made are not used")


@dataclass(frozen=True)
class Leaf:
    """A certificate for ``write_certificates`` to sign: the bundle directory it goes to, its common name, and what
    it is for: to serve (``server``, valid for ``hosts``), to connect (``client``), or both (a role of a Dask
    cluster, which listens and connects, docs/cluster.md)."""

    bundle: Path
    common_name: str
    server: bool = False
    client: bool = False
    hosts: tuple[str, ...] = ()


def write_certificates(leaves: Sequence[Leaf], valid_days: int, authority: str = "dmosim run CA") -> None:
    """A new CA (common name ``authority``), and a certificate it signs for each of ``leaves``, written to the
    leaf's bundle: ``cert.pem``, its key ``key.pem`` (0600) and the CA's ``ca.pem``. EC P-256 keys. The CA's key is
    not kept: nothing can be signed for these credentials later, so new ones replace them (a certificate cannot be
    revoked either)."""
    from cryptography import x509  # noqa: PLC0415  (only TLS needs it)
    from cryptography.hazmat.primitives import hashes, serialization  # noqa: PLC0415
    from cryptography.hazmat.primitives.asymmetric import ec  # noqa: PLC0415
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: PLC0415

    now = dt.datetime.now(dt.timezone.utc)
    start, end = now - dt.timedelta(minutes=5), now + dt.timedelta(days=valid_days)

    def name(common_name: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "dmosim"),
                          x509.NameAttribute(NameOID.COMMON_NAME, common_name)])

    def builder(subject: x509.Name, issuer: x509.Name, key) -> x509.CertificateBuilder:
        return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer).public_key(key.public_key())
                .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end))

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = name(authority)
    ca_cert = (builder(ca_name, ca_name, ca_key)
               .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                            content_commitment=False, key_encipherment=False, data_encipherment=False,
                                            key_agreement=False, encipher_only=False, decipher_only=False),
                              critical=True)
               .sign(ca_key, hashes.SHA256()))
    ca_pem = ca_cert.public_bytes(serialization.Encoding.PEM).decode()

    for leaf in leaves:
        key = ec.generate_private_key(ec.SECP256R1())
        usages = [*([ExtendedKeyUsageOID.SERVER_AUTH] if leaf.server else []),
                  *([ExtendedKeyUsageOID.CLIENT_AUTH] if leaf.client else [])]
        b = (builder(name(leaf.common_name), ca_name, key)
             .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
             .add_extension(x509.ExtendedKeyUsage(usages), critical=False))
        if leaf.hosts:
            b = b.add_extension(x509.SubjectAlternativeName([_alt_name(x509, h) for h in leaf.hosts]), critical=False)
        cert = b.sign(ca_key, hashes.SHA256())
        _write(leaf.bundle / CERT_FILE, cert.public_bytes(serialization.Encoding.PEM).decode(), public=True)
        _write(leaf.bundle / KEY_FILE, key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()).decode())
        _write(leaf.bundle / CA_FILE, ca_pem, public=True)


def _alt_name(x509, host: str):
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def _write(path: Path, text: str, *, public: bool = False) -> None:
    """Create the file, new (never through a link someone left there), readable by its owner only from the first
    byte on, or with ``public`` by anyone; writable by its owner only, whatever the umask."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
        os.fchmod(f.fileno(), 0o644 if public else 0o600)
