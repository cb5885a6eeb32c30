"""Recorders that join a day late still record everything its settlement needs: they ask the DMO for the traffic
they missed (docs/recording.md, "Late joiners"). Real processes, with the run's credentials and access control."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import threading

from dmosim.launch.processes import Roles, free_port, wait_listening
from messages import new_run_id
from messages.transport import Bus, BusConfig
from messages.recording import content_signature, read_recording
from messages.transport.access import bundle_settings
from messages.transport.credentials import create_auth_dir
from test_market_day import DAY, DEADLINES, ENV, ROOT, TINY, dmosim

READERS = ("recorder", "bidding", "noon", "blind", "watch")


def test_recorders_that_join_late_record_a_day_that_re_settles(tmp_path, fifo):
    run_id, port = new_run_id(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    auth = create_auth_dir(tmp_path / "auth", run_id, ["mg1", "mg2"], readers=READERS, dmo_client=False)
    common = ["--run-id", run_id, "--market-day", DAY]
    recordings = {name: tmp_path / f"{name}.mcap" for name in READERS[:4]}

    def record(roles, name, *extra):
        roles.start(name, dmosim("record", "--out", str(recordings[name]), "--run-id", run_id, "--connect", endpoint,
                                 "--auth-dir", str(auth), "--user", name, *extra),
                    log=tmp_path / f"{name}.log", env=ENV)

    with Roles() as roles:
        roles.start("dmo", dmosim("dmo", *common, "--listen", endpoint, "--agents", "2", "--subperiods", "1",
                                  "--auth-dir", str(auth), "--await-recorder", "60", *DEADLINES),
                    log=tmp_path / "dmo.log", env=ENV)
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
        record(roles, "recorder")  # from the start: the reference
        reached = {"bidding": threading.Event(), "noon": threading.Event(), "summary": threading.Event()}

        def hold(event: str) -> None:
            """The agents wait, frozen, until the late recorders of ``event`` record (an hour takes ms, a recorder
            seconds to start)."""
            if not reached[event].is_set():
                for agent in ("mg1", "mg2"):
                    roles.roles[agent].process.send_signal(signal.SIGSTOP)
                reached[event].set()

        def go_on() -> None:
            for agent in ("mg1", "mg2"):
                roles.roles[agent].process.send_signal(signal.SIGCONT)

        def on_clock(key, msg, at):
            if msg.phase == "bidding":
                hold("bidding")  # every agent has registered
            if msg.phase == "realtime" and msg.hour == 12:
                hold("noon")
            if msg.phase == "settlement":
                reached["summary"].set()

        config = BusConfig(mode="client", connect=(endpoint,), overrides=bundle_settings(auth, "watch"))
        with Bus(run_id, "watch", config, announce=False) as watch:
            watch.subscribe(watch.keys.clock(), on_clock)
            for i, agent in enumerate(("mg1", "mg2")):
                roles.start(agent, dmosim("agent", *common, "--id", agent, "--connect", endpoint, "--seed", str(i),
                                          "--auth-dir", str(auth), "--lease", "120", *TINY),
                            log=tmp_path / f"{agent}.log", env=ENV)
            assert reached["bidding"].wait(300), (tmp_path / "dmo.log").read_text()[-3000:]
            try:
                record(roles, "bidding", "--ready-file", str(fifo.path))
                assert fifo.line(roles.roles["bidding"].process.pid, 120) == str(recordings["bidding"])
            finally:
                go_on()
            assert reached["noon"].wait(600), (tmp_path / "dmo.log").read_text()[-3000:]
            try:
                record(roles, "noon", "--ready-file", str(fifo.path))
                record(roles, "blind", "--no-backfill", "--ready-file", str(fifo.path))
                # each says, once it records, where to: caught up (noon) and listening, both
                ready = {fifo.line(roles.roles[name].process.pid, 120) for name in ("noon", "blind")}
                assert ready == {str(recordings["noon"]), str(recordings["blind"])}
            finally:
                go_on()
            assert reached["summary"].wait(300)
        assert roles.roles["dmo"].process.wait(timeout=120) == 0, (tmp_path / "dmo.log").read_text()[-3000:]
        for name in recordings:
            roles.roles[name].process.send_signal(signal.SIGTERM)
            assert roles.roles[name].process.wait(timeout=60) == 0, (tmp_path / f"{name}.log").read_text()[-2000:]

    reference = read_recording(recordings["recorder"])
    backfilled = {}
    for name in ("bidding", "noon"):
        late = read_recording(recordings[name])
        assert content_signature(late) == content_signature(reference), name
        backfilled[name] = int(late.other_metadata["dmosim.backfill"]["messages"])
        assert settle(recordings[name]).returncode == 0
        info = json.loads(dmosim_out("info", str(recordings[name]), "--json"))
        assert info["missing"] == [] and info["backfilled_messages"] == backfilled[name]
    assert 0 < backfilled["bidding"] < backfilled["noon"]  # the registrations, then half a day more
    assert settle(recordings["recorder"]).returncode == 0

    # without the DMO's history, the recorder that joined at noon says what it lacks, and settle refuses in one line
    info = json.loads(dmosim_out("info", str(recordings["blind"]), "--json"))
    assert "mg1: no registration, no award recorded" in info["missing"]
    assert any(re.match(r"mg2: no meter report recorded for hour\(s\) 1-1\d, which", g) for g in info["missing"])
    out = settle(recordings["blind"])
    assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr
    assert "no awards recorded" in out.stderr or "no registration recorded" in out.stderr


def settle(path) -> subprocess.CompletedProcess:
    return subprocess.run(dmosim("settle", str(path)), capture_output=True, text=True, timeout=120, cwd=ROOT, env=ENV)


def dmosim_out(*args: str) -> str:
    out = subprocess.run(dmosim(*args), capture_output=True, text=True, timeout=120, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr
    return out.stdout
