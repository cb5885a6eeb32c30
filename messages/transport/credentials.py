"""Make the credentials of one run: a password per process, the router's user dictionary and access-control file
(access.py), and with TLS a CA, the router's certificate and one client certificate per process.

The layout of the directory is in access.py, which reads it back; every secret is created readable by its owner
only.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
import secrets
import shutil
from collections.abc import Sequence
from pathlib import Path

from scenarios.names import DMO

from ..keys import Keys
from .access import (ACL_FILE, CA_FILE, CERT_FILE, KEY_FILE, PASSWORD_FILE, READERS, USERS_FILE, AuthError,
                     access_control, check_names)

DEFAULT_HOSTS = ("localhost", "127.0.0.1")  # what the router's certificate is valid for, unless told


def create_auth_dir(out: str | os.PathLike, run_id: str, agents: Sequence[str], *, readers: Sequence[str] = READERS,
                    tls: bool = False, hosts: Sequence[str] = DEFAULT_HOSTS, valid_days: int = 30,
                    dmo_client: bool = True, overwrite: bool = False) -> Path:
    """Generate fresh credentials for one run: a random password per process, the router's dictionary and rules,
    and with ``tls`` a new CA with a certificate for the router (valid for ``hosts``) and one per process.
    Without ``dmo_client`` there are no credentials for the DMO: it must be the router itself."""
    out = Path(out)
    check_names(agents, readers)
    Keys(run_id)  # a bad run id fails here, not in the router
    if out.exists():
        if not out.is_dir():
            raise AuthError(f"{out} exists and is not a directory")
        if any(out.iterdir()):
            if not overwrite:
                raise AuthError(f"{out} is not empty; remove it or choose another directory")
            shutil.rmtree(out)
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    out.chmod(0o700)
    names = [DMO, *readers, *agents] if dmo_client else [*readers, *agents]
    passwords = {name: secrets.token_urlsafe(24) for name in names}
    for name in names:
        (out / name).mkdir(mode=0o700)
    _write_secret(out / USERS_FILE, "".join(f"{n}:{p}\n" for n, p in passwords.items()))
    acl = access_control(run_id, agents, readers, tls=tls, dmo_client=dmo_client)
    (out / ACL_FILE).write_text(json.dumps(acl, indent=2) + "\n")
    for name, password in passwords.items():
        _write_secret(out / name / PASSWORD_FILE, password + "\n")
    if tls:
        write_certificates(out, names, hosts, valid_days)
    return out


def write_certificates(out: Path, names: Sequence[str], hosts: Sequence[str], valid_days: int) -> None:
    """A CA for this auth directory, the router's server certificate for ``hosts`` and one client certificate per
    name (common name = the name, which the access-control subjects match). EC P-256 keys."""
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
        (bundle / CERT_FILE).write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        _write_secret(bundle / KEY_FILE, key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()).decode())
        (bundle / CA_FILE).write_bytes(ca_pem)

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
    save(out, *leaf(hosts[0], ExtendedKeyUsageOID.SERVER_AUTH, alt))
    for n in names:
        save(out / n, *leaf(n, ExtendedKeyUsageOID.CLIENT_AUTH))


def _alt_name(x509, host: str):
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def _write_secret(path: Path, text: str) -> None:
    """Create the file readable by its owner only, from the first byte on."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    path.chmod(0o600)
