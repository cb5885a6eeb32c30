"""A market in one process (``agents.hosting = "in-process"``, dmosim/launch/inprocess.py): the DMO's machine, the
agents' machines and the recorder driven with no network and no process, so it runs in the fast tier (as on one
core: the solves one after the other in this process, dmosim/launch/solves.py). What the processes give it gives
too: tests/system/test_determinism.py compares the two on one experiment."""

from __future__ import annotations

import json
import os

import pytest

from dmosim.cli import main
from dmosim.experiment.spec import parse_experiment
from dmosim.launch.local import run_experiment
from dmosim.results.report import Resettled, RunReport
from dmosim.results.tables import open_recording
from messages.recording import read_recording

TINY = {"seed": 3, "market_day": "2026-07-01", "agents": {"count": 2, "hosting": "in-process"},
        "market": {"subperiods": 1}, "schedule": {"scenarios": 1, "gap": 0.05}}


def on_cores(monkeypatch: pytest.MonkeyPatch, cores: int) -> None:
    """The market sees a machine of ``cores`` cores: as many solves run side by side, in worker processes when two or
    more."""
    monkeypatch.setattr(os, "cpu_count", lambda: cores)


@pytest.fixture(scope="module")
def day(tmp_path_factory):
    out = tmp_path_factory.mktemp("in-process") / "run"
    with pytest.MonkeyPatch.context() as monkeypatch:
        on_cores(monkeypatch, 1)
        return run_experiment(parse_experiment(TINY), out)


def schedules(result: RunReport) -> list[dict]:
    """The schedules the agents sent, without their envelope."""
    rec = read_recording(result.recording)
    return sorted((msg.model_dump(mode="json", exclude={"seq", "sent_at", "run", "incarnation"})
                   for _, msg in rec.decoded("schedule")), key=lambda m: m["sender"])


def test_a_day_in_one_process_settles_and_its_recording_re_settles_identically(day):
    assert day.verdict.ok, day.verdict
    assert day.recorded.complete and day.recorded.resettled == Resettled(identical=True, differences=[])
    rec = read_recording(day.recording)
    statements = {msg.agent: msg.total for _, msg in rec.decoded("settlement_statement")}
    assert statements == {a: day.settlement[a].total for a in ("mg1", "mg2")}
    # every agent operated its day and said so: 24 meter reports each, and its realised day
    assert sorted(msg.sender for _, msg in rec.decoded("meter_report")) == ["mg1"] * 24 + ["mg2"] * 24
    assert [d.market_day for d in day.realised["mg1"]] == ["2026-07-01"]
    # each message once: nothing is lost, so nothing is sent again
    assert day.realised["mg1"][0].messages.sent_again == 0 and day.received_again == 0


@pytest.mark.slow  # the solves side by side fork their workers
def test_the_solves_side_by_side_in_worker_processes_give_the_day_they_give_one_after_another(day, tmp_path,
                                                                                            monkeypatch):
    on_cores(monkeypatch, 2)
    side_by_side = run_experiment(parse_experiment(TINY), tmp_path / "run")
    assert side_by_side.verdict.ok, side_by_side.verdict
    assert side_by_side.settlement == day.settlement and schedules(side_by_side) == schedules(day)
    award = [c for c in side_by_side.realised["mg1"][0].compute if c.kind == "award"]
    assert len(award) == 1 and award[0].cpu_s > 0  # the worker's CPU, counted in the award's handling


def test_the_run_directory_holds_what_a_run_of_processes_gives(day):
    run_dir = day.run_dir
    assert json.loads(open(f"{run_dir}/result.json").read())["verdict"] == day.verdict.model_dump()
    assert "in-process" in open(f"{run_dir}/experiment.toml").read()
    assert open(f"{run_dir}/logs/market.log").read()  # the roles' log, one for the whole market


@pytest.mark.parametrize("flags, says", [
    (["--fault", "kill:mg1:3"], "has no processes to kill and no network to lose messages on"),
    (["--routers", "2"], "agents.routers: hosting \"in-process\" has no network"),
    (["--clock", "wall"], "deadlines.clock: hosting \"in-process\" runs on the logical clock only"),
    (["--tls"], "--tls: hosting \"in-process\" runs every role in this process"),
])
def test_what_needs_processes_or_a_network_is_refused_in_one_line(flags, says, capsys):
    assert main(["run", "--in-process", *flags, "--check"]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1, err


@pytest.fixture(scope="module")
def exporting_day(tmp_path_factory):
    """TINY on a seed whose islanded hour (hour 18) the agents were awarded exports in: P_M = 0 there is above the
    award, and the paper rule charges it."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        on_cores(monkeypatch, 1)
        return run_experiment(parse_experiment({**TINY, "seed": 11}), tmp_path_factory.mktemp("islanded") / "run")


def test_a_rule_that_reads_the_grid_exempts_exactly_the_islanded_hours_penalties(exporting_day, cli):
    """examples/islanding_rule.py re-settles the recorded day: each agent's bill is the paper rule's less the penalties
    its recorded statement charged in the hours the recorded grid states islanded (the recording's tables, summed
    here), and nothing else changes."""
    day = exporting_day
    hours = open_recording(day.recording)["hours"]
    assert hours["islanded"].any() and (hours[hours.islanded].deviation_penalty > 0).any()
    exempt = hours[hours.islanded].groupby("agent")[["deviation_penalty", "deviation_credit"]].sum()
    rule = "examples/islanding_rule.py:islanding_exempt"
    said = cli("settle", day.recording, "--rule", "paper", "--rule", rule, "--json")
    assert said.returncode == 0, said.stderr
    rows = {(r["agent"], r["rule"].split(":")[0] == "paper"): r for r in json.loads(said.stdout)["rows"]}
    for agent in ("mg1", "mg2"):
        paper, own = rows[agent, True], rows[agent, False]
        assert paper["change"] == 0 and own["energy_charge"] == paper["energy_charge"]
        assert own["deviation_penalty"] == pytest.approx(
            paper["deviation_penalty"] - exempt.loc[agent, "deviation_penalty"], abs=1e-9)
        assert own["total"] == pytest.approx(paper["total"] - exempt.loc[agent, "deviation_penalty"]
                                             + exempt.loc[agent, "deviation_credit"], abs=1e-9)
