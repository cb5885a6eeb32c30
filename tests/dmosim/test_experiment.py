"""Experiment files (dmosim/experiment/spec.py) and the run directory, without running a day: what a file may say,
how flags override it, and that bad input gets one line and exit 2."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from dmosim.cli import main
from dmosim.experiment.rundir import RunDir, RunDirError
from dmosim.experiment.spec import Experiment, ExperimentError, load_experiment, parse_experiment, to_toml, with_settings
from dmosim.experiment.sweep import parse_setting, variants
from dmosim.launch.roles import day_config

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_every_key_has_a_default_and_the_resolved_file_reads_back_the_same():
    week = load_experiment(EXAMPLES / "week.toml")
    assert week.days == 7 and week.profiles.load_scale[5] == 0.85 and week.market.subperiods == 1
    assert parse_experiment(tomllib.loads(to_toml(week))) == week
    assert parse_experiment({}) == Experiment() and Experiment().market.penalty is None  # None: the case's own
    swept = with_settings(week, {"seed": 2, "market.penalty": 50.0, "schedule.method": "benders"}, "--set")
    assert (swept.seed, swept.market.penalty, swept.schedule.method) == (2, 50.0, "benders")



def test_the_stochastic_day_example_is_the_feeder_fleet_at_paper_fidelity_and_checks(capsys):
    """Validated, not run: its day of 10 agents at 20 scenarios and 10-minute resolution takes tens of minutes on two
    cores (docs/benchmarks.md, "day"); tests/system/test_logical_time.py runs the same fleet on the same feeder
    shrunk to 1 scenario, hourly."""
    e = load_experiment(EXAMPLES / "stochastic-day.toml")
    assert (e.days, e.schedule.scenarios, e.market.subperiods, e.network.feeder) == (1, 20, 6, "ieee33")
    assert e.schedule.time_limit is None and e.deadlines.clock == "logical"  # the gap alone ends every solve
    assert Path(e.agents.fleet).samefile(EXAMPLES / "feeder-fleet.toml")
    assert main(["run", str(EXAMPLES / "stochastic-day.toml"), "--check"]) == 0
    assert "10 agents" in capsys.readouterr().out

@pytest.mark.parametrize("data, message", [
    ({"days": 0}, "days: Input should be greater than or equal to 1"),
    ({"market": {"mode": "auction"}}, "market.mode: Input should be 'bids' or 'fixed'"),
    ({"market": {"penalty": "150"}}, "market.penalty: Input should be a valid number"),
    ({"schedule": {"scenarioss": 3}}, "schedule.scenarioss: unknown key"),
    ({"market_day": "2026-02-30"}, "market_day: '2026-02-30' is not a date"),
    ({"profiles": {"load_scale": [1.0, -1.0]}}, "profiles.load_scale.1: Input should be greater than 0"),
    ({"market": {"settlement": "deadband:width=1"}}, "market.settlement: settlement rule deadband has no parameter"),
    ({"market": {"import_curve": [[4.0, 5.0], [2.0, 5.0]]}},
     "market: import_curve: the premiums must be >= 0 and strictly increasing, got [5.0, 5.0]"),
    ({"market": {"export_curve": [[4.0]]}}, "market.export_curve.0: List should have at least 2 items"),
    ({"market": {"export_curve": [[0.0, 1.0]]}}, "market: export_curve: every block must have MW > 0"),
    ({"market": {"import_curve": [[1.0, 0.0]], "mode": "fixed"}}, "market: import_curve and"),
    ({"deadlines": {"clock": "sundial"}}, "deadlines.clock: Input should be 'logical' or 'wall'"),
    ({"schedule": {"time_limit": 0}}, "schedule.time_limit: Input should be greater than 0"),
    ({"agents": {"hosting": "cloud"}}, "agents.hosting: Input should be 'auto', 'process', 'fork' or 'in-process'"),
])
def test_a_bad_experiment_is_one_line_naming_the_key(data, message):
    with pytest.raises(ExperimentError) as err:
        parse_experiment(data, "exp.toml")
    assert str(err.value).startswith(f"exp.toml: {message}") and "\n" not in str(err.value)
    with pytest.raises(ExperimentError, match="unknown key"):
        with_settings(Experiment(), {"market.pennalty": 1.0}, "--set")


def test_the_isos_curve_reads_back_and_a_price_no_message_carries_is_refused_at_check(tmp_path, capsys):
    curve = parse_experiment({"market": {"import_curve": [[4, 0], [2, 15.5]], "export_curve": [[3.0, 2.0]]}})
    assert curve.market.iso_curve.import_curve == ((4.0, 0.0), (2.0, 15.5))
    assert parse_experiment(tomllib.loads(to_toml(curve))) == curve
    assert day_config(curve).iso_curve == curve.market.iso_curve  # the DMO clears against it
    path = tmp_path / "exp.toml"
    path.write_text("[market]\nimport_curve = [[4, 0], [2, 15]]\n")
    assert main(["run", str(path), "--check"]) == 0 and "ISO's curve (2 import and 0 export blocks)" in capsys.readouterr().out
    path.write_text("[market]\nexport_curve = [[4, 0], [2, 2000]]\n")
    assert main(["run", str(path), "--check"]) == 2
    err = capsys.readouterr().err
    assert "beyond the prices messages carry (-1000 to 10000 $/MWh)" in err and err.count("\n") == 1


def test_flags_override_the_file(tmp_path, capsys):
    path = tmp_path / "exp.toml"
    path.write_text('seed = 3\ndays = 2\n[market]\npenalty = 80.0\n[agents]\ncount = 2\n')
    assert main(["run", str(path), "--check", "--days", "4", "--agents", "3", "--penalty", "0"]) == 0
    out = capsys.readouterr().out
    assert "4 day(s)" in out and "3 agents (mg1, mg2, mg3)" in out


@pytest.mark.parametrize("argv, says", [
    (["run", "nowhere.toml", "--check"], "experiment file not found: nowhere.toml"),
    (["run", "--days", "0", "--check"], "--days: expected an integer in 1..3,660"),
    (["run", "--fault", "kill:mg1:3:2", "--check"], "day 2 is past the run's 1 day(s)"),
    (["run", "--fault", "kill:mg7:3", "--check"], "unknown agent mg7"),
    (["run", "--from", "nothing.mcap", "--check"], "nothing.mcap: no such file"),
    (["run", "--settlement", "tests/dmo/test_rules.py:_raises", "--check"], "raised KeyError: 'mg1'"),
    (["dmo", "--agents", "1", "--settlement", "nosuch"], "market.settlement: unknown settlement rule 'nosuch'"),
    (["run", "--routers", "17", "--check"], "--routers: expected an integer in 0..16, got '17'"),
    (["run", "--fleet", "tests/data/router_named_fleet.toml", "--routers", "2", "--check"],
     "agents.routers = 2: host2 is the name of a router of the run and of an agent; rename the agent"),
])
def test_bad_input_to_run_is_one_line_and_exit_2(argv, says, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1, err


def test_a_bad_file_is_refused_before_anything_runs(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("exp.toml").write_text("[market]\nmode = 'auction'\n")
    assert main(["run", "exp.toml"]) == 2
    assert capsys.readouterr().err == "error: exp.toml: market.mode: Input should be 'bids' or 'fixed'\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.toml"]  # no run directory for a refused run


def test_a_run_directory_holding_a_run_is_not_overwritten_by_accident(tmp_path):
    rundir = RunDir.make(tmp_path / "r", "x")
    assert (rundir.root / "logs").is_dir() and rundir.recording.parent == rundir.root
    rundir.result.write_text("{}")
    with pytest.raises(RunDirError, match="not empty"):
        RunDir.make(tmp_path / "r", "x")
    assert RunDir.make(tmp_path / "r", "x", overwrite=True).root == tmp_path / "r"
    (tmp_path / "file").write_text("")
    with pytest.raises(RunDirError, match="not a directory"):
        RunDir.make(tmp_path / "file", "x")


# --- sweeps ------------------------------------------------------------------------------------------------------

def test_a_sweep_runs_every_combination_each_validated():
    settings = [parse_setting("market.penalty=100,300"), parse_setting("market.mode=bids,fixed"),
                parse_setting("profiles.load_scale=[1,0.8],[0.9]")]
    assert settings[2] == ("profiles.load_scale", [[1, 0.8], [0.9]])
    runs = variants(Experiment(), settings)
    assert len(runs) == 8 and len({v.label for v in runs}) == 8
    assert [(v.experiment.market.penalty, v.experiment.market.mode) for v in runs[::2]] == [
        (100.0, "bids"), (100.0, "fixed"), (300.0, "bids"), (300.0, "fixed")]
    assert runs[1].experiment.profiles.load_scale == [0.9] and runs[0].label.startswith("001-penalty=100-mode=bids")


@pytest.mark.parametrize("settings, says", [
    (["market.penalty"], "expected KEY=V1,V2"),
    (["market.penalty=1,1"], "a value is given twice"),
    (["market.penalty=1,", ], "an empty value"),
    (["market.penalty=-5"], "--set market.penalty=-5: market.penalty: Input should be greater than or equal to 0"),
    (["market.pennalty=5"], "unknown key"),
    (["seed=1,2", "seed=3"], "seed is swept twice"),
    (["market.settlement=paper,deadband:rate=-1"], "market.settlement: settlement rule deadband: rate must be"),
])
def test_a_bad_sweep_is_one_line_and_exit_2_before_anything_runs(tmp_path, capsys, settings, says):
    (tmp_path / "exp.toml").write_text("[agents]\ncount = 1\n")
    argv = ["sweep", str(tmp_path / "exp.toml"), "--out", str(tmp_path / "out")]
    assert main([*argv, *(flag for s in settings for flag in ("--set", s))]) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1, err
    assert not (tmp_path / "out").exists()


def test_sweep_check_lists_the_runs(tmp_path, capsys):
    (tmp_path / "exp.toml").write_text("[agents]\ncount = 1\n")
    assert main(["sweep", str(tmp_path / "exp.toml"), "--set", "seed=1,2,3", "--check"]) == 0
    out = capsys.readouterr().out
    assert "3 valid run(s)" in out and "003-seed=3" in out


@pytest.mark.parametrize("verb", [["run"], ["sweep", "--set", "seed=1,2"]])
def test_check_refuses_a_non_empty_out_as_the_run_would(verb, tmp_path, capsys):
    (tmp_path / "exp.toml").write_text("[agents]\ncount = 1\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "result.json").write_text("{}")
    argv = [verb[0], str(tmp_path / "exp.toml"), *verb[1:], "--out", str(out)]
    assert main(argv) == 2  # refused before anything starts
    refused = capsys.readouterr().err
    assert refused == f"error: {out} is not empty; choose another --out or pass --overwrite\n"
    assert main([*argv, "--check"]) == 2
    assert capsys.readouterr().err == refused
    assert main([*argv, "--check", "--overwrite"]) == 0
    assert [p.name for p in out.iterdir()] == ["result.json"]
