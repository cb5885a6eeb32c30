"""Make the credentials of one run: a password per process, the router's user dictionary and access-control file
(access.py), and with TLS a CA, the router's certificate and one client certificate per process; and check that
credentials found on disk are private to this user before any process uses them.

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
from collections.abc import Sequence
from pathlib import Path

from scenarios.names import DMO

from ..keys import Keys
from .access import (ACL_FILE, CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE, READERS, ROUTER_CERT_NAME, USERS_FILE,
                     AuthError, access_control)

DEFAULT_HOSTS = ("localhost", "127.0.0.1")  # what the router's certificate is valid for, unless told
SECRETS = (USERS_FILE, PASSWORD_FILE, KEY_FILE)  # files that hold a secret, wherever they are in a directory
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
    if not 1 <= valid_days <= MAX_CERT_DAYS:
        raise AuthError(f"certificates are valid for 1..{MAX_CERT_DAYS} days, not {valid_days}")
    Keys(run_id)  # a bad run id fails here, not in the router
    acl = access_control(run_id, agents, readers, tls=tls, dmo_client=dmo_client, routers=routers)  # checks names
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
    names = [*([DMO] if dmo_client else []), *readers, *routers, *agents]
    passwords = {name: secrets.token_urlsafe(24) for name in names}
    for name in names:
        (out / name).mkdir(mode=0o700)
    _write(out / USERS_FILE, "".join(f"{n}:{p}\n" for n, p in passwords.items()))
    _write(out / ACL_FILE, json.dumps(acl, indent=2) + "\n", public=True)
    for name, password in passwords.items():
        _write(out / name / PASSWORD_FILE, password)  # the password alone: what a client sends is the file
    if tls:
        write_certificates(out, names, hosts, valid_days)
    return out


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


def write_certificates(out: Path, names: Sequence[str], hosts: Sequence[str], valid_days: int) -> None:
    """A CA for this auth directory, the router's server certificate for ``hosts`` (common name ROUTER_CERT_NAME,
    which no client certificate has) and one client certificate per name (common name = the name, which the
    access-control subjects match). EC P-256 keys."""
    from cryptography import x509  # noqa: PLC0415  (only TLS needs it)
    from cryptography.hazmat.primitives import hashes, serialization  # noqa: PLC0415
    from cryptography.hazmat.primitives.asymmetric import ec  # noqa: PLC0415
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: PLC0415

    if not hosts:
        raise AuthError("TLS needs at least one host name or address for the router's certificate")
    now = dt.datetime.now(dt.timezone.utc)
    start, end = now - dt.timedelta(minutes=5), now + dt.timedelta(days=valid_days)

    def name(common_name: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "dmosim"),
                          x509.NameAttribute(NameOID.COMMON_NAME, common_name)])

    def builder(subject: x509.Name, issuer: x509.Name, key) -> x509.CertificateBuilder:
        return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer).public_key(key.public_key())
                .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end))

    def save(bundle: Path, cert, key) -> None:
        _write(bundle / CERT_FILE, cert.public_bytes(serialization.Encoding.PEM).decode(), public=True)
        _write(bundle / KEY_FILE, key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()).decode())
        _write(bundle / CA_FILE, ca_pem.decode(), public=True)

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = name("dmosim run CA")
    ca_cert = (builder(ca_name, ca_name, ca_key)
               .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                            content_commitment=False, key_encipherment=False, data_encipherment=False,
                                            key_agreement=False, encipher_only=False, decipher_only=False),
                              critical=True)
               .sign(ca_key, hashes.SHA256()))
    ca_pem = ca_cert.public_bytes(serialization.Encoding.PEM)

    def leaf(common_name: str, usage, alt_names=None):
        key = ec.generate_private_key(ec.SECP256R1())
        b = (builder(name(common_name), ca_name, key)
             .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
             .add_extension(x509.ExtendedKeyUsage([usage]), critical=False))
        if alt_names:
            b = b.add_extension(x509.SubjectAlternativeName(alt_names), critical=False)
        return b.sign(ca_key, hashes.SHA256()), key

    alt = [_alt_name(x509, host) for host in hosts]
    save(out, *leaf(ROUTER_CERT_NAME, ExtendedKeyUsageOID.SERVER_AUTH, alt))
    for n in names:
        save(out / n, *leaf(n, ExtendedKeyUsageOID.CLIENT_AUTH))


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
