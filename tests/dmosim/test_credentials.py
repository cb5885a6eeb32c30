"""Credentials as the roles find them (dmosim/cli/flags.py): a DMO, router or client refuses credentials someone else
could have made or changed, in one line naming the path; the default credentials directory is private; the run id
a router serves is unknown in advance and said; each verb's help says its own Zenoh mode; and a mesh's router logs in
to the router it connects to, as docs/hosts.md shows."""

from __future__ import annotations

import json
import os
import re
import shlex
from pathlib import Path

import pytest

from dmosim.console import UsageError
from dmosim.cli.flags import DEFAULT_CREDENTIALS, announce_run_id, bus_config, credentials_for, run_id_of
from dmosim.cli.main import build_parser, main
from dmosim.cli.router import check_relay_flags
from messages.keys import RUN_ID_PATTERN
from messages.transport.access import ACL_FILE, USERS_FILE
from messages.transport.credentials import create_auth_dir


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


def test_a_router_that_connects_to_another_logs_in_with_its_bundle_over_tls(tmp_path, monkeypatch, capsys):
    """A mesh's router (docs/hosts.md): it serves with the run's router files and logs in to the router it connects
    to with its own bundle; every inconsistent flag is one line and exit 2, and it never makes credentials."""
    monkeypatch.chdir(tmp_path)
    create_auth_dir(tmp_path / "mesh", "day1", ["mg1"], tls=True, routers=("host2",))
    create_auth_dir(tmp_path / "plain", "day1", ["mg1"])
    relay = ["router", "--run-id", "day1", "--listen", "tls/127.0.0.1:0", "--connect", "tls/127.0.0.1:7447"]
    args = build_parser("router").parse_args([*relay, "--auth-dir", "mesh", "--user", "host2"])
    credentials_for(args, "day1", ["mg1"], dmo_client=True)
    settings = dict(bus_config(args, "router", run_id="day1").overrides)
    assert json.loads(settings["transport/auth/usrpwd/user"]) == "host2"
    assert json.loads(settings["transport/link/tls/connect_certificate"]) == str((tmp_path / "mesh/host2/cert.pem"))
    assert json.loads(settings["transport/link/tls/listen_certificate"]) == str((tmp_path / "mesh/cert.pem"))
    assert json.loads(settings["access_control"])["enabled"]
    for flags, says in [
        ([*relay], "--connect: a router that connects to other routers joins their run; give it the run's"),
        (["router", *relay[3:], "--auth-dir", "mesh", "--user", "host2"], "give its --run-id"),
        ([*relay, "--agents", "2", "--auth-dir", "mesh", "--user", "host2"], "--agents: a router that connects"),
        ([*relay, "--auth-dir", "mesh"], "logs in to them: give --user NAME"),
        ([*relay, "--auth-dir", "mesh", "--user", "host9"], "mesh has no credentials for 'host9'"),
        ([*relay, "--auth-dir", "plain", "--user", "mg1"], "plain holds no TLS certificates"),
        ([*relay, "--auth-dir", "missing", "--user", "host2"], "missing/users.txt does not exist"),
        (["router", "--listen", "tls/127.0.0.1:0", "--auth-dir", "mesh", "--user", "host2"],
         "--user: a router logs in only to the routers it connects to"),
        ([*relay[:5], "--connect", "tcp/127.0.0.1:7447", "--auth-dir", "mesh", "--user", "host2"],
         "not tcp/127.0.0.1:7447"),
    ]:
        assert main(flags) == 2, flags
        err = capsys.readouterr().err
        assert says in err and err.count("\n") == 1, (flags, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh", "plain"]  # a router that connects made nothing


def test_the_commands_docs_hosts_md_gives_are_the_tools_own():
    doc = (Path(__file__).resolve().parents[2] / "docs" / "hosts.md").read_text()
    commands = [line for block in re.findall(r"```bash\n(.*?)```", doc, re.S) for line in block.splitlines()
                if line.startswith("dmosim ")]
    assert len(commands) >= 6
    for command in commands:
        verb, *flags = shlex.split(command)[1:]
        args = build_parser(verb).parse_args([verb, *flags])  # an unknown flag exits here
        if verb == "router":
            check_relay_flags(args)
