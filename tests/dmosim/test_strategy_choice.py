"""Choosing bidding strategies (docs/strategies.md, "Choosing one"): for all agents by the experiment's
``agents.strategy``, for one by its fleet entry, swept, and refused in one line with exit 2 before anything runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from dmosim.cli import main
from dmosim.cli.checks import check_inputs
from dmosim.experiment.spec import Experiment, ExperimentError, load_experiment, parse_experiment
from dmosim.experiment.sweep import parse_setting, variants
from dmosim.launch.roles import fleet_of, strategy_of
from scenarios.fleet import FleetError, load_fleet

HERE = "tests.microgrid_agent.test_strategies"


def test_the_default_is_the_price_response_and_a_sweep_of_strategies_resolves_each_variant():
    assert Experiment().agents.strategy == "price-response"
    runs = variants(Experiment(), [parse_setting("agents.strategy=naive,table1")])
    assert [(v.label, v.experiment.agents.strategy) for v in runs] == [("001-strategy=naive", "naive"),
                                                                      ("002-strategy=table1", "table1")]
    quoted = variants(Experiment(), [parse_setting('agents.strategy="table1:scale=0.5","examples/strategy.py:Shaded:'
                                                   'shade=0.5,memory=3"')])
    assert [v.experiment.agents.strategy for v in quoted] == ["table1:scale=0.5",
                                                              "examples/strategy.py:Shaded:shade=0.5,memory=3"]
    with pytest.raises(ExperimentError, match="agents.strategy: unknown strategy 'best'"):
        variants(Experiment(), [parse_setting("agents.strategy=naive,best")])


def test_an_experiment_naming_a_strategy_is_checked_as_a_name_and_never_imports_it(tmp_path):
    (tmp_path / "mine.py").write_text("raise SystemExit('imported')\n")
    experiment = parse_experiment({"agents": {"strategy": f"{tmp_path}/mine.py:Mine:shade=0.5"}})
    assert experiment.agents.strategy == f"{tmp_path}/mine.py:Mine:shade=0.5"
    with pytest.raises(ExperimentError, match="^x: agents.strategy: strategy table1 has no parameter 'width'"):
        parse_experiment({"agents": {"strategy": "table1:width=2"}}, "x")


def test_a_fleet_entry_chooses_its_own_strategy_over_the_experiments(tmp_path):
    (tmp_path / "fleet.toml").write_text('[[agents]]\nid = "a"\nstrategy = "table1:scale=0.5"\n\n'
                                         '[[agents]]\nid = "b"\n')
    (tmp_path / "exp.toml").write_text('[agents]\nfleet = "fleet.toml"\nstrategy = "naive"\n')
    experiment = load_experiment(tmp_path / "exp.toml")
    fleet = check_inputs(experiment)
    assert [m.strategy for m in fleet] == ["table1:scale=0.5", None]
    assert [strategy_of(experiment, m) for m in fleet_of(experiment)] == ["table1:scale=0.5", "naive"]


@pytest.mark.parametrize("entry, message", [
    ("strategy = 3", "agents[a].strategy: must be a strategy's name of 1..500 characters, got 3"),
    ('strategy = ""', "agents[a].strategy: must be a strategy's name of 1..500 characters"),
])
def test_a_fleet_entry_whose_strategy_is_no_name_is_refused(tmp_path, entry, message):
    (tmp_path / "fleet.toml").write_text(f'[[agents]]\nid = "a"\n{entry}\n')
    with pytest.raises(FleetError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_fleet(tmp_path / "fleet.toml")


def test_a_fleet_naming_an_unknown_strategy_is_refused_naming_the_file_and_the_agent(tmp_path):
    (tmp_path / "fleet.toml").write_text('[[agents]]\nid = "a"\nstrategy = "best"\n')
    experiment = parse_experiment({"agents": {"fleet": str(tmp_path / "fleet.toml")}})
    with pytest.raises(ExperimentError, match=r"fleet.toml: agents\[a\].strategy: unknown strategy 'best'"):
        check_inputs(experiment)


@pytest.mark.parametrize("argv, says", [
    (["run", "--strategy", "best", "--check"], "flags: agents.strategy: unknown strategy 'best'"),
    (["run", "--agents", "1", "--strategy", f"{HERE}:Raises", "--check"],
     f"--strategy: strategy {HERE}:Raises failed: ZeroDivisionError: no such luck"),
    (["run", "--agents", "1", "--strategy", "tests/no_such.py:C", "--check"], "no file tests/no_such.py"),
    (["sweep", "examples/week.toml", "--set", f"agents.strategy=naive,{HERE}:TooShort", "--check"],
     f": agents.strategy: strategy {HERE}:TooShort returned no bid: 23 hours of steps, not 24"),
    (["agent", "--id", "mg1", "--run-id", "r1", "--strategy", "table1:scale=-1"],
     "agents.strategy: strategy table1: scale must be in [0, 10], got -1"),
])
def test_a_strategy_that_cannot_be_used_is_one_line_and_exit_2(argv, says, capsys, monkeypatch):
    monkeypatch.chdir(Path(__file__).resolve().parents[2])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1, err


def test_run_check_takes_the_built_ins_and_a_strategy_of_ones_own(capsys, monkeypatch):
    monkeypatch.chdir(Path(__file__).resolve().parents[2])
    assert main(["run", "--agents", "1", "--strategy", f"{HERE}:Flat:mw=2", "--check"]) == 0
    assert f"bidding with {HERE}:Flat:mw=2, 0 fault(s)" in capsys.readouterr().out
