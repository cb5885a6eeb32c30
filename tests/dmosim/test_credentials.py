"""Credentials as the roles find them (dmosim/cli/flags.py): a DMO, router or client refuses credentials someone else
could have made or changed, in one line naming the path; the default credentials directory is private; the run id
a router serves is unknown in advance and said; and each verb's help says its own Zenoh mode."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest

from dmosim.console import UsageError
from dmosim.cli.flags import DEFAULT_CREDENTIALS, announce_run_id, bus_config, credentials_for, run_id_of
from dmosim.cli.main import build_parser
from messages.keys import RUN_ID_PATTERN
from messages.transport.access import ACL_FILE, USERS_FILE


@pytest.fixture
def loose_umask():
    """A umask that leaves new files group-writable, as many systems set it."""
    old = os.umask(0o002)
    yield
    os.umask(old)


def dmo_args(tmp_path: Path, *flags: str):
    return build_parser("dmo").parse_args(["dmo", "--agents", "1", "--listen", "tcp/127.0.0.1:0", *flags])


def planted(where: Path, run_id: str) -> Path:
    """What an attacker leaves where a DMO will look: open to all, with rules that allow an extra user anything."""
    where.mkdir(parents=True)
    where.chmod(0o777)
    (where / USERS_FILE).write_text("mg1:x\nintruder:secret\n")
    (where / USERS_FILE).chmod(0o666)
    acl = {"enabled": True, "default_permission": "allow", "rules": [{"key_exprs": [f"dmosim/{run_id}/**"]}]}
    (where / ACL_FILE).write_text(json.dumps(acl))
    return where


def test_a_dmo_refuses_credentials_planted_where_it_looks(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    planted(tmp_path / DEFAULT_CREDENTIALS / "day", "day")
    with pytest.raises(UsageError, match=f"{DEFAULT_CREDENTIALS}/day is writable by its group"):
        credentials_for(dmo_args(tmp_path, "--run-id", "day"), "day", ["mg1"], dmo_client=False)
    planted(tmp_path / "given", "r2")
    args = dmo_args(tmp_path, "--auth-dir", "given")
    with pytest.raises(UsageError, match="given is writable by its group"):
        credentials_for(args, "r2", ["mg1"], dmo_client=False)
    with pytest.raises(UsageError, match="given is writable by its group"):  # nor does a client log in with them
        bus_config(build_parser("agent").parse_args(["agent", "--id", "mg1", "--auth-dir", "given"]), "client", "mg1")


def test_the_default_credentials_directory_is_made_private_and_checked(tmp_path, monkeypatch, loose_umask):
    monkeypatch.chdir(tmp_path)
    args = dmo_args(tmp_path)
    run_id = run_id_of(args)
    credentials_for(args, run_id, ["mg1"], dmo_client=False)
    assert Path(args.auth_dir) == Path(DEFAULT_CREDENTIALS) / run_id
    assert (tmp_path / DEFAULT_CREDENTIALS).stat().st_mode & 0o777 == 0o700
    again = dmo_args(tmp_path, "--run-id", run_id)  # a restarted DMO finds its own credentials and takes them
    credentials_for(again, run_id, ["mg1"], dmo_client=False)
    assert again.auth_dir == args.auth_dir
    (tmp_path / DEFAULT_CREDENTIALS).chmod(0o777)
    with pytest.raises(UsageError, match=f"{DEFAULT_CREDENTIALS} is writable by its group"):
        credentials_for(dmo_args(tmp_path, "--run-id", run_id), run_id, ["mg1"], dmo_client=False)


def test_a_password_file_others_may_read_is_refused(tmp_path):
    secret = tmp_path / "pw"
    secret.write_text("s3cret")
    secret.chmod(0o644)
    args = build_parser("agent").parse_args(["agent", "--id", "mg1", "--password-file", str(secret)])
    with pytest.raises(UsageError, match="pw is readable by others"):
        bus_config(args, "client", "mg1")
    secret.chmod(0o600)
    assert dict(bus_config(args, "client", "mg1").overrides)["transport/auth/usrpwd/password"] == '"s3cret"'


@pytest.mark.parametrize("verb", ["dmo", "router", "credentials"])
def test_a_run_id_nobody_chose_is_new_each_time_and_said(verb, capsys):
    given = ["--agents", "1"] if verb == "dmo" else ["--out", "x"] if verb == "credentials" else []
    first, second = (build_parser(verb).parse_args([verb, *given]) for _ in range(2))
    assert first.run_id is None
    ids = run_id_of(first), run_id_of(second)
    assert ids[0] != ids[1] and all(re.match(RUN_ID_PATTERN, i) for i in ids)
    announce_run_id(first)
    assert f"--run-id {ids[0]}" in capsys.readouterr().err
    chosen = build_parser(verb).parse_args([verb, *given, "--run-id", "day1"])
    assert run_id_of(chosen) == "day1"
    announce_run_id(chosen)
    assert capsys.readouterr().err == ""  # a run id the user chose needs no saying
    with pytest.raises(UsageError, match="--run-id: run id 'a/b' must match"):
        run_id_of(build_parser(verb).parse_args([verb, *given, "--run-id", "a/b"]))


@pytest.mark.parametrize("verb, mode", [("dmo", "router"), ("router", "router"), ("agent", "client"),
                                        ("record", "client"), ("replay", "peer; router with --as-dmo")])
def test_mode_help_says_each_verbs_own_default(verb, mode, capsys):
    with pytest.raises(SystemExit):
        build_parser(verb).parse_args([verb, "--help"])
    flat = "".join(capsys.readouterr().out.split())  # argparse wraps lines, even within --as-dmo
    assert "".join(f"zenoh session mode (default: {mode})".split()) in flat
