"""End to end: the DMO and agents as real OS processes over real Zenoh, on tiny models.

Every process a test starts is stopped in a ``finally`` (``Roles`` as a context manager), on free ports and
under a fresh run prefix, so tests never cross and nothing is left behind when one fails.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pandas as pd
import pytest

from dmosim.launch.processes import Roles, free_port, wait_listening
from messages.keys import new_run_id
from messages.transport import Bus, BusConfig
from messages.transport.access import bundle_settings
from messages.transport.credentials import create_auth_dir
from scenarios.case import load_case

ROOT = Path(__file__).resolve().parents[2]
DAY = "2026-07-01"
TINY = ["--scenarios", "1", "--gap", "0.05", "--time-limit", "60"]
DEADLINES = ["--registration-timeout", "60", "--bid-timeout", "120", "--schedule-timeout", "120",
             "--hour-timeout", "60"]
ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


def dmosim(*args: str) -> list[str]:
    return [sys.executable, "-m", "dmosim", *args]


def ended(argv: list[str], *, timeout: float, **popen) -> subprocess.CompletedProcess:
    """``subprocess.run(argv, capture_output=True, text=True, timeout=...)`` for a command that starts processes of
    its own (``dmosim run``: a DMO, agents, a recorder): it runs in a session of its own, and if it outlasts
    ``timeout`` every process of that session is killed, not only the command, and the test fails."""
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         **popen)
    try:
        out, err = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        kill_session(p.pid)
        out, err = p.communicate()
        pytest.fail(f"{' '.join(argv[2:5])} ... outlasted {timeout:g} s; its stderr: {err[-3000:]}")
    return subprocess.CompletedProcess(argv, p.returncode, out, err)


def kill_session(sid: int) -> None:
    """SIGKILL every process of session ``sid`` (read from /proc: its roles lead process groups of their own)."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid:
            with contextlib.suppress(ProcessLookupError):
                os.kill(int(stat.parent.name), signal.SIGKILL)


class Tap:
    """A passive observer of one run: keeps every valid message by kind, once (an agent sends a payload again while
    its receipt is on its way: the same sender, process and number), and signals milestones."""

    def __init__(self, bus: Bus):
        self.messages: dict[str, list] = {}
        self.heard: set[tuple[str, int, int]] = set()
        self.lock = threading.Lock()
        self.summary = threading.Event()
        self.hour_reached: dict[int, threading.Event] = {h: threading.Event() for h in range(1, 25)}
        bus.subscribe(bus.keys.everything(), self.on_message)

    def on_message(self, key, msg, received_at):
        with self.lock:
            if (msg.sender, msg.incarnation, msg.seq) in self.heard:
                return
            self.heard.add((msg.sender, msg.incarnation, msg.seq))
            self.messages.setdefault(msg.kind, []).append(msg)
        if msg.kind == "clock" and msg.hour:
            self.hour_reached[msg.hour].set()
        if msg.kind == "day_summary":
            self.summary.set()

    def of(self, kind: str) -> list:
        with self.lock:
            return list(self.messages.get(kind, []))


def recompute(awards, prices, meters, penalty, subperiods, caps):
    """Settlement from first principles, independent of dmo/settlement.py: per hour, price x award, plus
    c x max(P_M - P_sch, 0) x dt per sub-period; a missing report counts every sub-period at the agent's cap."""
    out = {}
    for agent, award in awards.items():
        energy = penalty_total = 0.0
        for h in range(24):
            energy += round(prices[h] * award[h], 2)
            readings = meters.get((agent, h + 1), [caps[agent]] * subperiods)
            over = sum(max(p - award[h], 0.0) for p in readings) / subperiods
            penalty_total += round(penalty * over, 2)
        out[agent] = (round(energy, 2), round(penalty_total, 2))
    return out


def run_day(tmp_path, agents=("mg1", "mg2"), extra_dmo=(), kill=None, extra_agent=(), env=ENV):
    """Start a DMO and agents (with ``extra_agent`` flags, in ``env``); optionally SIGKILL one agent when the clock
    reaches an hour. Returns the tap and the DMO's result."""
    run_id, port = new_run_id(), free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    result = tmp_path / "result.json"
    common = ["--run-id", run_id, "--market-day", DAY]
    auth = create_auth_dir(tmp_path / "auth", run_id, list(agents), readers=("tap",), dmo_client=False)
    with Roles() as roles:
        roles.start("dmo", dmosim("dmo", *common, "--listen", endpoint, "--agents", str(len(agents)),
                                  "--subperiods", "1", "--result", str(result), "--auth-dir", str(auth), *DEADLINES,
                                  *extra_dmo), log=tmp_path / "dmo.log", env=ENV)
        wait_listening(port, 60, lambda: roles.roles["dmo"].process.poll() is None)
        tap_config = BusConfig(mode="client", connect=(endpoint,), overrides=bundle_settings(auth, "tap"))
        with Bus(run_id, "tap", tap_config, announce=False) as bus:
            tap = Tap(bus)
            for i, agent in enumerate(agents):
                roles.start(agent, dmosim("agent", *common, "--id", agent, "--connect", endpoint, "--seed", str(i),
                                          "--lease", "1", "--auth-dir", str(auth), *TINY, *extra_agent),
                            log=tmp_path / f"{agent}.log", env=env)
            if kill:
                agent, hour = kill
                assert tap.hour_reached[hour].wait(300), "the day never reached the kill hour"
                roles.kill(agent)
            assert tap.summary.wait(600), (tmp_path / "dmo.log").read_text()[-3000:]
        code = roles.roles["dmo"].process.wait(timeout=60)
        assert code == 0, (tmp_path / "dmo.log").read_text()[-3000:]
    return tap, json.loads(result.read_text())


def test_two_agents_settle_as_recomputed_from_awards_and_meter_reports(tmp_path):
    tap, result = run_day(tmp_path)
    awards = {m.agent: m.p_sch_mw for m in tap.of("award")}
    assert set(awards) == {"mg1", "mg2"}
    prices = tap.of("award")[0].clearing_price_per_mwh
    meters = {(m.sender, m.hour): m.p_m_mw for m in tap.of("meter_report")}
    assert len(meters) == 48
    for m in tap.of("meter_report"):
        assert m.deviation_mw == pytest.approx([p - awards[m.sender][m.hour - 1] for p in m.p_m_mw])
    caps = {r.sender: r.max_import_mw for r in tap.of("registration")}
    expected = recompute(awards, prices, meters, load_case("paper").grid.penalty, 1, caps)
    for st in tap.of("settlement_statement"):
        assert (st.energy_charge, st.deviation_penalty) == pytest.approx(expected[st.agent], abs=0.011)
        assert result["settlement"][st.agent]["total"] == pytest.approx(st.total, abs=1e-9)
    assert len(tap.of("schedule")) == 2 and len(tap.of("grid_state")) == 24
    assert result["rejected_messages"] == 0 and result["incidents"] == []


def test_an_agent_killed_mid_day_is_settled_by_the_missing_data_rule(tmp_path):
    tap, result = run_day(tmp_path, kill=("mg2", 5))
    reported = {m.hour for m in tap.of("meter_report") if m.sender == "mg2"}
    # killed once the clock reached hour 5 (hours 1-4 reported); the clock may run a few hours on before SIGKILL lands
    assert reported == set(range(1, max(reported) + 1)) and 4 <= max(reported) < 24
    st = {s.agent: s for s in tap.of("settlement_statement")}
    assert st["mg1"].missing_subperiods == 0
    assert st["mg2"].missing_subperiods == 24 - len(reported)
    assert any(i["agent"] == "mg2" and "vanished" in i["reason"] for i in result["incidents"])


def test_an_agent_leaves_only_once_it_has_its_own_statement(tmp_path):
    """The DMO's statements are held back 2 s (a message fault), so each agent has the day summary first: it asks
    for its statement, and its day ends with it (what its strategy learned of the day, written to a file)."""
    observed = tmp_path / "observed"
    observed.mkdir()
    strategy = f"{ROOT / 'tests' / 'data' / 'observing_strategy.py'}:Observing"
    tap, result = run_day(tmp_path, extra_dmo=("--fault", "delay:dmo/statement/*:2"),
                          extra_agent=("--strategy", strategy), env={**ENV, "DMOSIM_TEST_OBSERVED": str(observed)})
    for agent in ("mg1", "mg2"):
        (learned,) = [json.loads(line) for line in (observed / f"{agent}.jsonl").read_text().splitlines()]
        assert learned == {"market_day": DAY, "statement_total": result["settlement"][agent]["total"]}


def test_dmosim_run_prints_the_summary_and_json(tmp_path):
    argv = dmosim("run", "--agents", "2", "--subperiods", "1", *TINY, *DEADLINES, "--out", str(tmp_path), "--json")
    out = ended(argv, timeout=900, cwd=ROOT, env=ENV)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout)
    for key in ("run_id", "recording", "agents", "clearing_prices", "awards", "settlement", "rejected_messages",
                "incidents"):
        assert key in result
    assert result["agents"] == ["mg1", "mg2"] and len(result["clearing_prices"]) == 24
    assert set(result["settlement"]["mg1"]) >= {"energy_charge", "deviation_penalty", "total"}
    assert "24/24 hours (100%), done" in out.stderr
    # the run directory holds what the run made: the experiment, recording, result, tables and figure
    assert Path(result["recording"]).samefile(tmp_path / "recording.mcap")  # recording is on by default
    assert json.loads((tmp_path / "result.json").read_text())["settlement"] == result["settlement"]
    assert "[agents]\ncount = 2" in (tmp_path / "experiment.toml").read_text()
    hours = pd.read_csv(tmp_path / "tables" / "hours.csv")
    for agent, total in hours.groupby("agent")["total"].sum().items():
        assert total == pytest.approx(result["settlement"][agent]["total"], abs=0.01)
    per_hour = hours.drop_duplicates("hour").set_index("hour")["congestion"]
    assert [per_hour[h] for h in range(1, 25)] == result["congestion"]  # as the DMO's clearing says
    # what each agent realised came as its agent_day, into the result and the tables alike, never from a log
    agent_days = pd.read_csv(tmp_path / "tables" / "agent_days.csv").set_index("agent")
    for agent in ("mg1", "mg2"):
        (day,) = result["realised"][agent]
        assert day["day"] == 1 and agent_days.loc[agent, "total"] == pytest.approx(day["total"])
        assert {e["hour"] for e in day["compute"] if e["kind"] == "grid_state"} == set(range(1, 25))
    assert (tmp_path / "run.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and result["figure"].endswith("run.png")
    assert (tmp_path / "logs" / "mg1.log").is_file()


def test_bad_fault_and_fleet_exit_2(tmp_path):
    for flags in (["--fault", "kill:mg9:3"], ["--fault", "melt:mg1:3"], ["--fleet", str(tmp_path / "none.toml")]):
        out = subprocess.run(dmosim("run", "--agents", "2", *flags), capture_output=True, text=True, timeout=60,
                             cwd=ROOT, env=ENV)
        assert out.returncode == 2 and out.stderr.count("\n") == 1, out.stderr


def test_an_agent_with_nobody_to_connect_to_says_so_in_one_line():
    port = free_port()
    out = subprocess.run(dmosim("agent", "--id", "mg1", "--run-id", new_run_id(), "--connect",
                                f"tcp/127.0.0.1:{port}", "--connect-timeout", "1", "--quiet"),
                         capture_output=True, text=True, timeout=60, cwd=ROOT, env=ENV)
    assert out.returncode == 1 and out.stderr.count("\n") == 1, out.stderr
    assert f"could not connect to tcp/127.0.0.1:{port} within 1 s" in out.stderr
    out = subprocess.run(dmosim("agent", "--id", "mg1", "--connect-timeout", "-1"), capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=ENV)
    assert out.returncode == 2 and "connect_timeout_s" in out.stderr and out.stderr.count("\n") == 1, out.stderr
