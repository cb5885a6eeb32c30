"""Authentication and access control: Zenoh's own, enforced by the DMO's router (messages/transport/access.py).

The DMO and agents run as real processes with per-run credentials; the attacks come from sessions in this process
that hold a real agent's credentials. Every process is stopped by ``Roles`` whatever happens, on free ports and
under fresh run ids.
"""

from __future__ import annotations

import json
import queue
import stat
import subprocess

import pytest

from dmosim.launch.processes import Roles, free_port, wait_listening
from messages import HOURS, Award, Bid, BidStep, GridState, MeterReport, encode, new_run_id
from messages.transport import Bus, BusConfig
from messages.transport.access import (AGENT_TOPICS, AuthError, access_control, auth_settings, bundle_settings,
                                       client_settings, router_settings)
from messages.transport.credentials import create_auth_dir
from scenarios.case import load_case
from test_market_day import DAY, DEADLINES, ENV, TINY, dmosim, recompute

MARK = 77.7  # what no honest process ever sends: any message carrying it is a forgery


# --- the rules and the credentials, without a network ---------------------------------------------------------

def _grants(acl: dict, subject: str) -> list[dict]:
    (policy,) = [p for p in acl["policies"] if p["subjects"] == [subject]]
    return [r for r in acl["rules"] if r["id"] in policy["rules"]]


def _keys(grants, message: str, flow: str) -> set[str]:
    return {k for r in grants if message in r["messages"] and flow in r["flows"] for k in r["key_exprs"]}


def test_rules_give_each_agent_its_own_keys_and_the_public_topics_only():
    acl = access_control("r1", ["mg1", "mg2"], ["recorder"])
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert all(r["permission"] == "allow" for r in acl["rules"])
    mg1 = _grants(acl, "mg1")
    assert _keys(mg1, "put", "ingress") == {f"dmosim/r1/agent/mg1/{t}" for t in AGENT_TOPICS}
    hears = {f"dmosim/r1/dmo/{t}" for t in ("call_for_bids", "clock", "grid", "network", "summary", "award/mg1",
                                             "statement/mg1", "receipt/mg1")}
    assert _keys(mg1, "declare_subscriber", "ingress") == hears == _keys(mg1, "put", "egress")
    assert _keys(mg1, "liveliness_token", "ingress") == {"dmosim/r1/alive/mg1"}
    assert not any("mg2" in k for r in mg1 for k in r["key_exprs"])
    assert _keys(mg1, "query", "ingress") == hears == _keys(mg1, "reply", "egress")  # asking the DMO
    assert not any(m in r["messages"] for r in mg1 for m in ("delete", "declare_queryable"))
    recorder = _grants(acl, "recorder")
    assert _keys(recorder, "declare_subscriber", "ingress") == {"dmosim/r1/**"}
    assert _keys(recorder, "query", "ingress") == {"dmosim/r1/**"}  # the DMO's history of the day
    assert not _keys(recorder, "put", "ingress")  # hears everything, says nothing
    assert {s["id"]: s["usernames"] for s in acl["subjects"]} == {"dmo": ["dmo"], "recorder": ["recorder"],
                                                                  "mg1": ["mg1"], "mg2": ["mg2"]}
    tls = access_control("r1", ["mg1"], tls=True)
    assert all(s["cert_common_names"] == s["usernames"] for s in tls["subjects"])
    assert "dmo" not in {s["id"] for s in access_control("r1", ["mg1"], dmo_client=False)["subjects"]}
    with pytest.raises(AuthError):
        access_control("r1", ["mg1", "recorder"])


def test_credentials_are_random_private_and_bound_to_their_run(tmp_path):
    auth = create_auth_dir(tmp_path / "auth", "r1", ["mg1", "mg2"])
    assert stat.S_IMODE(auth.stat().st_mode) == 0o700
    users = dict(line.split(":", 1) for line in (auth / "users.txt").read_text().splitlines())
    assert set(users) == {"dmo", "recorder", "mg1", "mg2"} and len(set(users.values())) == 4
    for name, password in users.items():
        assert len(password) >= 24 and (auth / name / "password").read_text().strip() == password
        assert stat.S_IMODE((auth / name / "password").stat().st_mode) == 0o600
    assert stat.S_IMODE((auth / "users.txt").stat().st_mode) == 0o600
    settings = dict(router_settings(auth, "r1"))
    assert json.loads(settings["access_control"]) == json.loads((auth / "access_control.json").read_text())
    assert json.loads(settings["transport/auth/usrpwd/dictionary_file"]) == str((auth / "users.txt").resolve())
    with pytest.raises(AuthError, match="another run"):
        router_settings(auth, "r2")
    with pytest.raises(AuthError, match="not empty"):
        create_auth_dir(auth, "r1", ["mg1"])
    with pytest.raises(AuthError, match="no credentials"):
        bundle_settings(auth, "mg3")
    settings = dict(auth_settings(str(auth), None, None, "mg1", router=False))
    assert json.loads(settings["transport/auth/usrpwd/user"]) == "mg1"
    assert json.loads(settings["transport/auth/usrpwd/password"]) == users["mg1"]
    explicit = (None, "mg2", str(auth / "mg2" / "password"))  # --user and --password-file
    assert dict(auth_settings(*explicit, "mg1", router=False))["transport/auth/usrpwd/user"] == '"mg2"'
    with pytest.raises(AuthError, match="router"):
        auth_settings(*explicit, None, router=True)
    assert auth_settings(None, None, None, "mg1", router=False) == ()  # no flags: an open network


def test_tls_credentials_need_tls_endpoints(tmp_path):
    auth = create_auth_dir(tmp_path / "auth", "r1", ["mg1"], tls=True)
    args = (str(auth), None, None)  # --auth-dir
    assert dict(auth_settings(*args, "mg1", router=False, endpoints=["tls/127.0.0.1:7447"]))[
        "transport/link/tls/enable_mtls"] == "true"
    with pytest.raises(AuthError, match="tls/"):
        auth_settings(*args, "mg1", router=False, endpoints=["tcp/127.0.0.1:7447"])
    with pytest.raises(AuthError, match="tls/"):
        auth_settings(*args, None, router=True, run_id="r1", endpoints=["tcp/127.0.0.1:7447"])


# --- joining --------------------------------------------------------------------------------------------------

def _refused(run_id: str, endpoint: str, overrides=()) -> None:
    config = BusConfig(mode="client", connect=(endpoint,), overrides=tuple(overrides))
    with pytest.raises(ConnectionError, match="or it refused us"):
        Bus(run_id, "mg1", config, announce=False).open().close()


def test_a_dmo_given_no_credentials_makes_them_and_admits_only_their_holders(tmp_path):
    run_id, port = new_run_id(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    common = ["--run-id", run_id, "--market-day", DAY]
    made = tmp_path / "dmosim-credentials" / run_id  # in the directory it was started in
    with Roles() as roles:
        roles.start("dmo", dmosim("dmo", *common, "--listen", endpoint, "--agents", "1", "--subperiods", "1",
                                  *DEADLINES), log=tmp_path / "dmo.log", env=ENV, cwd=tmp_path)
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)  # with them: made before
        assert sorted(p.name for p in made.iterdir() if p.is_dir()) == ["mg1", "recorder"]
        _refused(run_id, endpoint)                                                           # an open door no more
        roles.start("mg1", dmosim("agent", *common, "--id", "mg1", "--connect", endpoint, "--auth-dir", str(made),
                                  *TINY), log=tmp_path / "mg1.log", env=ENV)
        assert roles.roles["dmo"].process.wait(timeout=300) == 0, (tmp_path / "dmo.log").read_text()[-3000:]
        assert roles.roles["mg1"].process.wait(timeout=60) == 0
    both = subprocess.run(dmosim("dmo", "--agents", "1", "--insecure", "--auth-dir", str(made)), capture_output=True,
                          text=True, timeout=60, env=ENV, cwd=tmp_path)
    assert both.returncode == 2 and both.stderr.count("\n") == 1 and "--insecure" in both.stderr, both.stderr


def test_over_tls_only_a_certificate_of_the_run_and_the_right_password_join(tmp_path):
    run_id, port = new_run_id(), free_port()
    endpoint = f"tls/127.0.0.1:{port}"
    auth = create_auth_dir(tmp_path / "auth", run_id, ["mg1", "mg2"], tls=True)
    stranger = create_auth_dir(tmp_path / "stranger", run_id, ["mg1"], tls=True)  # another CA
    with Roles() as roles:
        roles.start("dmo", dmosim("dmo", "--run-id", run_id, "--market-day", DAY, "--listen", endpoint, "--agents",
                                  "1", "--auth-dir", str(auth), *DEADLINES), log=tmp_path / "dmo.log", env=ENV)
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
        _refused(run_id, endpoint)                                                          # nothing at all
        _refused(run_id, endpoint, client_settings("mg1", auth / "mg1" / "password"))       # password, no cert
        _refused(run_id, endpoint, client_settings("mg1", auth / "mg2" / "password", auth / "mg1"))  # wrong password
        _refused(run_id, endpoint, client_settings("mg1", auth / "mg1" / "password", stranger / "mg1"))  # foreign CA
        config = BusConfig(mode="client", connect=(endpoint,), overrides=bundle_settings(auth, "mg1"))
        with Bus(run_id, "mg1", config) as mg1:
            assert "dmo" in mg1.present(timeout_s=5.0)
        assert roles.roles["dmo"].process.poll() is None


# --- a day under attack ---------------------------------------------------------------------------------------

def _forged_bid(sender: str) -> Bid:
    return Bid(sender=sender, market_day=DAY, hours=[[BidStep(price_per_mwh=MARK, quantity_mw=5.0)]] * HOURS)


def _forged_meter(sender: str, hour: int) -> MeterReport:
    return MeterReport(sender=sender, market_day=DAY, hour=hour, subperiods=1, p_m_mw=(MARK,), deviation_mw=(MARK,))


def _forged_award(agent: str) -> Award:
    return Award(sender="dmo", market_day=DAY, agent=agent, p_sch_mw=(MARK,) * HOURS,
                 clearing_price_per_mwh=(MARK,) * HOURS, penalty_per_mwh=0.0, subperiods=1, rules_version=1,
                 rules="forged")


def test_an_agent_can_neither_speak_for_nor_listen_to_another(tmp_path):
    """mg1's credentials in the hands of an attacker: bids, meter reports, awards and grid states forged for mg2 or
    the DMO are dropped by the router before anyone sees them, mg2's award and statement never reach it, and a
    message that claims mg2 as sender on mg1's own key gets through the router only to be refused by the DMO."""
    run_id, port = new_run_id(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    result_file = tmp_path / "result.json"
    auth = create_auth_dir(tmp_path / "auth", run_id, ["mg1", "mg2"], readers=("recorder", "tap"))
    common = ["--run-id", run_id, "--market-day", DAY]

    def client(name: str) -> BusConfig:
        return BusConfig(mode="client", connect=(endpoint,), overrides=bundle_settings(auth, name))

    with Roles() as roles:
        roles.start("dmo", dmosim("dmo", *common, "--listen", endpoint, "--agents", "2", "--subperiods", "1",
                                  "--result", str(result_file), "--auth-dir", str(auth), *DEADLINES),
                    log=tmp_path / "dmo.log", env=ENV)
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
        _refused(run_id, endpoint)                                                           # no credentials
        _refused(run_id, endpoint, client_settings("mg1", auth / "mg2" / "password"))        # wrong password
        _refused(run_id, endpoint, client_settings("mallory", auth / "mg1" / "password"))    # unknown user

        seen: dict[str, list] = {}
        events: queue.Queue = queue.Queue()
        spied: list[tuple[str, str]] = []
        heard: set[tuple[str, int, int]] = set()

        def on_tap(key, msg, at):
            if (msg.sender, msg.incarnation, msg.seq) in heard:
                return  # a payload sent again while its receipt was on its way
            heard.add((msg.sender, msg.incarnation, msg.seq))
            seen.setdefault(msg.kind, []).append(msg)
            if msg.kind in ("call_for_bids", "award", "day_summary") or (msg.kind == "clock" and msg.hour == 3):
                events.put(msg)

        with Bus(run_id, "tap", client("tap"), announce=False) as tap, \
                Bus(run_id, "mg1", client("mg1"), announce=False) as spy, \
                Bus(run_id, "mg1", client("mg1"), announce=False) as forger:
            tap.subscribe(tap.keys.everything(), on_tap)
            k = spy.keys
            for pattern in (k.award("mg1"), k.award("mg2"), k.statement("mg2"), k.award("*"), k.dmo_all(),
                            k.everything(), k.rejected()):
                spy.subscribe(pattern, lambda key, msg, at, p=pattern: spied.append((p, key)))
            for i, agent in enumerate(("mg1", "mg2")):
                roles.start(agent, dmosim("agent", *common, "--id", agent, "--connect", endpoint, "--seed", str(i),
                                          "--lease", "1", "--auth-dir", str(auth), *TINY),
                            log=tmp_path / f"{agent}.log", env=ENV)
            forged_award = False
            while True:
                msg = events.get(timeout=600)
                if msg.kind == "call_for_bids":      # before mg2 has solved its own bid
                    forger.publish_raw(k.bid("mg2"), encode(_forged_bid("mg2")))
                elif msg.kind == "award" and not forged_award:
                    forged_award = True
                    forger.publish_raw(k.award("mg2"), encode(_forged_award("mg2")))
                elif msg.kind == "clock":            # hour 3 starts
                    forger.publish_raw(k.meter("mg2"), encode(_forged_meter("mg2", 3)))
                    forger.publish_raw(k.grid(), encode(GridState(sender="dmo", market_day=DAY, hour=3, subperiods=1,
                                                                  connected=(False,))))
                    forger.publish_raw(k.meter("mg1"), encode(_forged_meter("mg2", 3)))  # on its own key
                elif msg.kind == "day_summary":
                    break
        assert roles.roles["dmo"].process.wait(timeout=60) == 0, (tmp_path / "dmo.log").read_text()[-3000:]
    result = json.loads(result_file.read_text())

    # Nothing forged reached anyone: the router dropped it (the tap hears everything the router passes on).
    assert sorted(b.sender for b in seen["bid"]) == ["mg1", "mg2"]
    assert all(step.price_per_mwh != MARK for b in seen["bid"] for hour in b.hours for step in hour)
    assert sorted(a.agent for a in seen["award"]) == ["mg1", "mg2"]
    assert all(MARK not in a.p_sch_mw for a in seen["award"])
    assert len(seen["grid_state"]) == 24 and [g.hour for g in seen["grid_state"]] == list(range(1, 25))
    meters = {(m.sender, m.hour): m.p_m_mw for m in seen["meter_report"]}
    assert len(seen["meter_report"]) == 48 and all(MARK not in p for p in meters.values())

    # The one forgery the rules let through (mg1's own key) was refused by the DMO's check, and recorded as such.
    (rejection,) = seen["rejection"]
    assert rejection.code == "unauthorised" and rejection.key == f"{k.prefix}/agent/mg1/meter"
    assert result["rejected_messages"] == 1
    assert len(result["incidents"]) == 1 and "may not publish" in result["incidents"][0]["reason"]

    # The victim is settled on its own reports alone.
    awards = {a.agent: a.p_sch_mw for a in seen["award"]}
    caps = {r.sender: r.max_import_mw for r in seen["registration"]}
    expected = recompute(awards, seen["award"][0].clearing_price_per_mwh, meters, load_case("paper").grid.penalty, 1,
                         caps)
    statements = {s.agent: s for s in seen["settlement_statement"]}
    for agent in ("mg1", "mg2"):
        assert statements[agent].missing_subperiods == 0
        assert (statements[agent].energy_charge, statements[agent].deviation_penalty) == pytest.approx(
            expected[agent], abs=0.011)
        assert result["settlement"][agent]["total"] == pytest.approx(statements[agent].total, abs=1e-9)

    # mg1's credentials never heard mg2's award or statement, nor anything through a wider pattern.
    # (The wider patterns are refused by the router; they only see, inside the spy's own session, what arrives for
    # its one allowed subscription.)
    # Nor the DMO's rejections, even of the forgery on its own key: those are for readers (its own refusals come in
    # its receipts), so one agent's refused junk reaches no other agent.
    assert {key for _, key in spied} == {k.award("mg1")}
    assert {p for p, _ in spied} <= {k.award("mg1"), k.award("*"), k.dmo_all(), k.everything()}
