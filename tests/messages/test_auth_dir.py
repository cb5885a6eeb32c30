"""Credentials on disk (messages/transport/credentials.py): made private whatever the umask, the password file
holding the password alone, credentials that someone else could have made or changed refused in one line naming
the path and what is wrong, a mesh's routers' (docs/hosts.md), certificates for what each role does, and a bundle
carried to another host."""

from __future__ import annotations

import json
import os

import pytest
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID

from messages.transport.access import ACL_FILE, PASSWORD_FILE, ROUTER_CERT_NAME, USERS_FILE, AuthError, read_password
from messages.transport.credentials import (BUNDLE_FILES, MAX_CERT_DAYS, MAX_HOSTS, MAX_READERS, Leaf, check_private,
                                            create_auth_dir, read_bundle, write_bundle, write_certificates)


@pytest.fixture
def loose_umask():
    """A umask that leaves new files group-writable, as many systems set it."""
    old = os.umask(0o002)
    yield
    os.umask(old)


def test_credentials_are_private_whatever_the_umask(tmp_path, loose_umask):
    auth = create_auth_dir(tmp_path / "auth", "r1", ["mg1"], tls=True)
    modes = {str(p.relative_to(auth)): p.stat().st_mode & 0o777 for p in [auth, *auth.rglob("*")]}
    assert modes["."] == 0o700 and modes["mg1"] == 0o700
    assert modes[USERS_FILE] == modes["key.pem"] == modes["mg1/password"] == modes["mg1/key.pem"] == 0o600
    assert modes[ACL_FILE] == modes["cert.pem"] == modes["mg1/ca.pem"] == 0o644
    check_private(auth)  # what dmosim makes, it accepts


def test_the_password_file_holds_the_password_alone_and_an_old_bundles_newline_is_read_past(tmp_path):
    auth = create_auth_dir(tmp_path / "auth", "r1", ["mg1"])
    password = (auth / "mg1" / PASSWORD_FILE).read_text()
    assert password and "\n" not in password and f"mg1:{password}\n" in (auth / USERS_FILE).read_text()
    old = tmp_path / "old-password"
    old.write_text(password + "\n")  # a bundle made before: the newline is not the password's
    assert read_password(old) == password


@pytest.mark.parametrize("where, mode, says", [
    (".", 0o777, r"auth is writable by its group \(mode 0777\)"),
    (".", 0o702, r"auth is writable by everyone \(mode 0702\)"),
    (USERS_FILE, 0o666, r"users.txt is writable by its group"),
    (USERS_FILE, 0o640, r"users.txt is readable by others \(mode 0640\): a secret must be its owner's alone"),
    ("mg1", 0o770, r"auth/mg1 is writable by its group"),
    ("mg1/password", 0o644, r"mg1/password is readable by others"),
    (ACL_FILE, 0o664, r"access_control.json is writable by its group"),
])
def test_credentials_anyone_else_could_change_are_refused(tmp_path, where, mode, says):
    auth = create_auth_dir(tmp_path / "auth", "r1", ["mg1"])
    (auth / where).chmod(mode)
    with pytest.raises(AuthError, match=says):
        check_private(auth)
    (auth / ACL_FILE).chmod(0o644)  # a public file may be read by anyone
    (auth / where).chmod(0o700 if (auth / where).is_dir() else 0o600)
    check_private(auth)


def test_credentials_another_user_made_are_refused(tmp_path, monkeypatch):
    auth = create_auth_dir(tmp_path / "auth", "r1", ["mg1"])
    monkeypatch.setattr(os, "getuid", lambda: os.stat(auth).st_uid + 1)  # as seen by someone else
    with pytest.raises(AuthError, match=r"auth is owned by user \d+, not by this user"):
        check_private(auth)
    (tmp_path / "empty").mkdir()
    with pytest.raises(AuthError, match="empty is owned by user"):  # nor is their empty directory filled in
        create_auth_dir(tmp_path / "empty", "r1", ["mg1"])


def test_what_credentials_are_made_for_is_bounded(tmp_path):
    with pytest.raises(AuthError, match=f"valid for 1..{MAX_CERT_DAYS} days"):
        create_auth_dir(tmp_path / "a", "r1", ["mg1"], tls=True, valid_days=MAX_CERT_DAYS + 1)
    readers = tuple(f"r{i}" for i in range(MAX_READERS + 1))
    with pytest.raises(AuthError, match=f"at most {MAX_READERS} readers"):
        create_auth_dir(tmp_path / "b", "r1", ["mg1"], readers=readers)
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_a_mesh_s_routers_relay_the_whole_run_and_know_the_router_they_connected_to_by_its_certificate(tmp_path):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    auth = create_auth_dir(tmp_path / "auth", "r1", ["mg1"], tls=True, routers=("host2", "host3"))
    acl = json.loads((auth / ACL_FILE).read_text())
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert subjects["host2"] == {"id": "host2", "usernames": ["host2"], "cert_common_names": ["host2"]}
    # the router a router connected to has no user name on that link: only the routers' certificate names it
    assert subjects[ROUTER_CERT_NAME] == {"id": ROUTER_CERT_NAME, "cert_common_names": [ROUTER_CERT_NAME]}
    for subject in ("host2", "host3", ROUTER_CERT_NAME, "dmo"):
        (policy,) = [p for p in acl["policies"] if p["subjects"] == [subject]]
        (rule,) = [r for r in acl["rules"] if r["id"] in policy["rules"]]
        assert rule["key_exprs"] == ["dmosim/r1/**"] and set(rule["flows"]) == {"ingress", "egress"}
        assert {"put", "declare_subscriber", "liveliness_token", "query", "reply"} <= set(rule["messages"])

    def common_name(path):
        cert = x509.load_pem_x509_certificate(path.read_bytes())
        return cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value

    assert common_name(auth / "cert.pem") == ROUTER_CERT_NAME  # the routers' own, which no process is named
    assert {common_name(c) for c in auth.glob("*/cert.pem")} == {"dmo", "recorder", "mg1", "host2", "host3"}
    assert (auth / "host3" / PASSWORD_FILE).is_file() and "host3:" in (auth / USERS_FILE).read_text()


def test_a_mesh_needs_tls_and_routers_named_apart(tmp_path):
    with pytest.raises(AuthError, match="only over mutual TLS"):
        create_auth_dir(tmp_path / "a", "r1", ["mg1"], routers=("host2",))
    with pytest.raises(AuthError, match="router name 'mg1' must"):
        create_auth_dir(tmp_path / "b", "r1", ["mg1"], tls=True, routers=("mg1",))
    with pytest.raises(AuthError, match="must be unique"):
        create_auth_dir(tmp_path / "c", "r1", ["mg1"], tls=True, readers=("tap",), routers=("TAP",))
    with pytest.raises(AuthError, match=f"at most .* {MAX_HOSTS} routers"):
        create_auth_dir(tmp_path / "d", "r1", ["mg1"], tls=True, routers=[f"h{i}" for i in range(MAX_HOSTS + 1)])
    assert not any((tmp_path / d).exists() for d in "abcd")


def usages(path) -> set[str]:
    """What the certificate at ``path`` may be used for: serve, connect, or both."""
    cert = x509.load_pem_x509_certificate(path.read_bytes())
    names = {ExtendedKeyUsageOID.SERVER_AUTH: "serve", ExtendedKeyUsageOID.CLIENT_AUTH: "connect"}
    return {names[u] for u in cert.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value}


def test_one_maker_signs_each_certificate_for_what_its_role_does(tmp_path):
    run = create_auth_dir(tmp_path / "run", "r1", ["mg1"], tls=True)
    assert usages(run / "cert.pem") == {"serve"} and usages(run / "mg1" / "cert.pem") == {"connect"}
    (tmp_path / "both").mkdir()
    write_certificates([Leaf(tmp_path / "both", "a dask worker", server=True, client=True)], 1, "a cluster's CA")
    assert usages(tmp_path / "both" / "cert.pem") == {"serve", "connect"}
    assert oct((tmp_path / "both" / "key.pem").stat().st_mode & 0o777) == "0o600"


def test_a_bundle_carried_elsewhere_is_the_same_and_as_private(tmp_path, loose_umask):
    run = create_auth_dir(tmp_path / "run", "r1", ["mg1", "mg2"], tls=True)
    files = read_bundle(run, "mg1")
    assert sorted(files) == sorted(BUNDLE_FILES)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir(mode=0o700)
    write_bundle(elsewhere, "mg1", files)
    assert read_bundle(elsewhere, "mg1") == files and [p.name for p in elsewhere.iterdir()] == ["mg1"]
    check_private(elsewhere)
    assert (elsewhere / "mg1" / PASSWORD_FILE).stat().st_mode & 0o777 == 0o600
    with pytest.raises(AuthError, match="users.txt is not a file of a bundle"):
        write_bundle(elsewhere, "mg2", {USERS_FILE: "mg1:x\n"})
