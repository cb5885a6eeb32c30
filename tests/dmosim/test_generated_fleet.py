"""An experiment that generates its fleet (``agents.generate``, ``--generate``) and ``dmosim fleet``: bad values are one
line and exit 2, ``--check`` draws and validates the fleet, and a run writes it into its run directory, where every
role reads it; without running a market day."""

from __future__ import annotations

import json

import pytest

from dmosim.cli import main
from dmosim.experiment.spec import load_experiment, parse_experiment, to_toml
from dmosim.launch.roles import agent_config, fleet_of, member_of, resolved
from scenarios.diverse import generate_fleet
from scenarios.fleet import load_fleet, member_case


@pytest.mark.parametrize("argv, file, says", [
    (["run", "--generate", "0", "--check"], None, "--generate: expected an integer in 1..1,024"),
    (["run", "--generate", "3", "--agents", "2", "--check"], None, "--agents and --generate exclude each other"),
    (["run", "--generate", "5", "--agents", "3", "--check"], None, "--agents and --generate exclude each other"),
    (["run", "exp.toml", "--agents", "3", "--check"], "[agents]\ngenerate = 2\n", "--agents and agents.generate"),
    (["run", "exp.toml", "--generate", "3", "--check"], "[agents]\ncount = 2\n", "count and generate exclude"),
    (["run", "exp.toml", "--check"], "[agents]\ngenerate = 3\nfleet = 'f.toml'\n", "fleet and generate exclude"),
    (["run", "exp.toml", "--check"], "[agents]\ngenerate = 'many'\n", "exp.toml: agents.generate: Input should be"),
    (["run", "exp.toml", "--fleet", "f.toml", "--check"], "[agents]\ngenerate = 2\n", "fleet and generate exclude"),
    (["run", "--generate", "3", "--fault", "kill:mg4:2", "--check"], None, "unknown agent mg4"),
    (["dmo", "--generate", "2", "--agents", "2"], None, "--agents and --generate exclude each other"),
    (["fleet", "--agents", "0"], None, "--agents: expected an integer in 1..1,024"),
    (["fleet", "--agents", "2", "--feeder", "nowhere"], None, "nowhere': not a built-in"),
    (["fleet", "--agents", "2", "--out", "."], None, "is a directory"),
])
def test_bad_values_are_one_line_and_exit_2_and_nothing_is_written(argv, file, says, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    if file:
        (tmp_path / "exp.toml").write_text(file)
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_check_draws_and_validates_the_fleet_and_writes_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--generate", "4", "--seed", "2", "--check"]) == 0
    assert "4 agents (mg1, mg2, mg3, mg4) drawn diverse from seed 2" in capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []


def test_a_sweep_checks_each_generated_fleet_of_its_own(tmp_path, capsys):
    """Variants of two sizes: the one of 2 agents has no mg3 to kill (a fleet checked once per file or count and
    seed would have been taken for the other's)."""
    (tmp_path / "exp.toml").write_text('faults = ["kill:mg3:2"]\n[agents]\ngenerate = 3\n')
    assert main(["sweep", str(tmp_path / "exp.toml"), "--set", "agents.generate=3,2", "--check"]) == 2
    assert "unknown agent mg3" in capsys.readouterr().err


def test_a_run_writes_its_fleet_into_its_run_directory_and_every_role_reads_it(tmp_path, monkeypatch, capsys):
    started = {}

    def launch(experiment, run_id, rundir, **_):  # where the roles would start: the run as they would be given it
        rundir.experiment.write_text(to_toml(experiment))
        started.update(experiment=experiment, rundir=rundir)
        raise RuntimeError("stopped before any role starts")

    monkeypatch.setattr("dmosim.cli.run.run_locally", launch)
    monkeypatch.chdir(tmp_path)
    argv = ["run", "--generate", "5", "--seed", "4", "--feeder", "feeder5", "--out", "run", "--no-record"]
    assert main(argv) == 1 and "stopped before any role starts" in capsys.readouterr().err
    rundir, experiment = started["rundir"], started["experiment"]
    assert experiment.agents.generate is None and experiment.agents.fleet == str(rundir.fleet.resolve())
    assert sorted(p.name for p in (rundir.root / "cases").iterdir()) == [f"mg{i}.toml" for i in range(1, 6)]
    drawn = generate_fleet(5, seed=4)
    written = load_fleet(rundir.fleet.resolve())
    assert [member_case(m) for m in written] == [m.drawn for m in drawn]
    assert [m.seed for m in written] == [m.seed for m in drawn]
    assert [m.bus for m in written] == experiment.network.buses  # placed as the run places them, written down

    role = resolved(load_experiment(rundir.experiment))  # what `dmosim dmo|agent --experiment` reads
    assert [(m.id, m.case, m.seed, m.bus) for m in fleet_of(role)] == [(m.id, m.case, m.seed, m.bus) for m in written]
    mg3 = member_of(role, "mg3")
    assert member_case(mg3) == drawn[2].drawn and agent_config(role, mg3).bus == experiment.network.buses[2]


def test_a_role_given_the_generating_experiment_draws_the_same_fleet():
    experiment = resolved(parse_experiment({"seed": 9, "agents": {"generate": 3}}))
    assert [member_case(m) for m in fleet_of(experiment)] == [m.drawn for m in generate_fleet(3, seed=9)]


def test_dmosim_fleet_writes_the_fleet_a_run_would_and_keeps_what_is_there(tmp_path, capsys):
    out = tmp_path / "fleets" / "f.toml"
    argv = ["fleet", "--agents", "5", "--seed", "4", "--feeder", "feeder5", "--out", str(out)]
    assert main([*argv, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    placed = resolved(parse_experiment({"seed": 4, "agents": {"generate": 5}, "network": {"feeder": "feeder5"}}))
    assert [r["bus"] for r in printed["members"]] == placed.network.buses
    assert [r["id"] for r in printed["members"]] == [f"mg{i}" for i in range(1, 6)]
    fleet = load_fleet(out)
    assert [member_case(m) for m in fleet] == [m.drawn for m in generate_fleet(5, seed=4)]
    before = out.read_text()
    assert main(argv) == 2
    assert capsys.readouterr().err == f"error: {out} exists; choose another --out or pass --overwrite\n"
    out.unlink()
    assert main(argv) == 2 and "cases/mg1.toml exists" in capsys.readouterr().err  # a case file is kept too
    assert main([*argv, "--overwrite"]) == 0 and out.read_text() == before
    assert "wrote" in capsys.readouterr().out


def test_dmosim_fleet_json_without_out_writes_nothing_and_prints_what_it_would_write(tmp_path, monkeypatch, capsys):
    argv = ["fleet", "--agents", "4", "--seed", "4", "--feeder", "feeder5", "--json"]
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 0
    printed = json.loads(capsys.readouterr().out)
    assert list(tmp_path.iterdir()) == []
    assert (printed["fleet"], printed["cases"], printed["seed"]) == (None, None, 4)
    assert main([*argv, "--out", "f.toml"]) == 0  # the same fleet, written and read back
    assert json.loads(capsys.readouterr().out)["members"] == printed["members"]
