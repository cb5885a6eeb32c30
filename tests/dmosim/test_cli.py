"""The ``dmosim`` command line as a user meets it: JSON output, and one-line errors with exit 2 for bad input.

Each command runs in this process through ``main``, what the executable calls (the ``cli`` fixture); only what needs a
fresh interpreter (which package ``python -m dmosim`` imports) starts one, in the slow tier."""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import jsonschema
import pytest

from dmosim.cli import main, native_stdout_to_stderr
from dmosim.console import UsageError, shadowing
from dmosim.cli.flags import add_bus_flags, bus_config
from messages import KINDS, PHASES, SCHEMA_VERSION, MeterReport, encode
from messages.transport import BusConfig
from microgrid_agent.solvers.routes import auto_threshold, resolve_method
from scenarios.case import DATA_DIR


def test_solve_json_has_the_spec_keys(cli):
    out = cli("solve", "--subperiods", "1", "--scenarios", "2", "--gap", "0.01", "--json")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    for key in ("status", "objective", "cost_breakdown", "commitment", "mip_gap", "bound", "scenarios", "timings"):
        assert key in result
    assert set(result["cost_breakdown"]) == {"generation", "startup", "curtailment", "penalty"}
    assert set(result["commitment"]) == {"G1", "G2", "G3", "G4"}
    assert all(len(v) == 24 and set(v) <= {0, 1} for v in result["commitment"].values())
    assert set(result["timings"]) == {"build_s", "solve_s", "total_s"}
    assert result["bound"] <= result["objective"] and result["mip_gap"] <= 0.01 + 1e-9
    assert result["verified"] is True
    breakdown = sum(result["cost_breakdown"].values())
    assert breakdown == pytest.approx(result["objective"], rel=1e-9)


def test_a_decomposed_solve_reports_each_iteration_on_stderr_ending_at_its_result(cli):
    out = cli("solve", "--method", "benders", "--subperiods", "1", "--scenarios", "3", "--gap", "0.01", "--json",
                 "--workers", "1")
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    lines = [ln for ln in out.stderr.splitlines() if ln.startswith("dmosim: benders ")]
    assert any("LP relaxation, iteration" in ln for ln in lines)
    last = lines[-1]
    assert "integer master, iteration" in last
    bound, best = (float(x.replace(",", "")) for x in re.findall(r"(?:bound|best) ([\d,]+\.\d\d)", last))
    assert best == pytest.approx(result["objective"], abs=0.01)
    assert bound == pytest.approx(result["bound"], abs=0.01)
    assert (best - bound) / best <= 0.01 + 1e-9


def test_stdout_carries_only_what_dmosim_prints_native_writes_go_to_stderr(capfd):
    # HiGHS 1.16 prints a banner on file descriptor 1 whenever a solver is created; --json output must survive it.
    # capfd holds file descriptors 1 and 2 and sys.stdout for the test, and gives all three back after it.
    native_stdout_to_stderr()
    ours = sys.stdout
    try:
        os.write(1, b"native banner\n")
        print('{"ours": 1}')
    finally:
        ours.close()
    out = capfd.readouterr()
    assert json.loads(out.out) == {"ours": 1}
    assert "native banner" in out.err


def test_infinite_penalty_is_written_as_a_string(cli):
    out = cli("solve", "--subperiods", "1", "--scenarios", "1", "--penalty", "inf", "--json")
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout)["penalty"] == "inf"


def _paper() -> dict:
    return tomllib.loads((DATA_DIR / "paper.toml").read_text())


def _write_toml(path: Path, data: dict) -> Path:
    """A minimal TOML writer for the case's shapes (tables, arrays of tables, scalars, lists, inline dicts)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + "}"
        return repr(v)

    lines = []
    for section, body in data.items():
        for item in body if isinstance(body, list) else [body]:
            lines.append(f"[[{section}]]" if isinstance(body, list) else f"[{section}]")
            lines += [f"{k} = {value(v)}" for k, v in item.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def _mutate(data: dict, where: str, new) -> dict:
    node, *path = where.split(".")
    target = data[node]
    for part in path[:-1]:
        target = target[int(part)] if part.isdigit() else target[part]
    if new is _DELETE:
        del target[path[-1]]
    else:
        target[path[-1]] = new
    return data


_DELETE = object()


@pytest.mark.parametrize("where,new,expected", [
    ("grid.penalty", _DELETE, "grid.penalty: missing field"),
    ("units.2.p_min", 3.5, "units[G3]: p_min (3.5) > p_max (3.0)"),
    ("loads.0.beta", 25, "loads[L1].beta"),
    ("loads.0.energy", 9.0, "loads[L1]: energy 9.0 MWh cannot be delivered"),
    ("units.0.cost", -1.0, "units[G1].cost"),
    ("fixed_load.forecast", [1.0] * 23, "fixed_load.forecast"),
])
def test_bad_case_file_exits_2_with_one_line_naming_the_field(cli, tmp_path, where, new, expected):
    case = _write_toml(tmp_path / "bad.toml", _mutate(_paper(), where, new))
    out = cli("solve", "--case", str(case), "--subperiods", "1", "--scenarios", "1")
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr
    assert expected in out.stderr and "bad.toml" in out.stderr


def test_written_case_round_trips(cli, tmp_path):
    """The TOML writer above is faithful, so the failures above come from the mutation alone."""
    case = _write_toml(tmp_path / "same.toml", _paper())
    out = cli("solve", "--case", str(case), "--subperiods", "1", "--scenarios", "1", "--json")
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("content", ["this is not toml = = =", "\x00\x01binary"])
def test_unreadable_case_file_exits_2(cli, tmp_path, content):
    path = tmp_path / "junk.toml"
    path.write_text(content)
    out = cli("solve", "--case", str(path))
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "Traceback" not in out.stderr


@pytest.mark.parametrize("flags", [
    ["--scenarios", "0"], ["--scenarios", "many"], ["--subperiods", "-2"], ["--island-hours", "25"],
    ["--penalty", "-5"], ["--penalty", "nan"], ["--gap", "2"], ["--transfer-scale", "x"], ["--case", "nope"],
    ["--no-such-flag"], ["--cost-convention", "weird"], ["--method", "simplex"], ["--workers", "0"],
    ["--islanding", "even"], ["--replications", "0"], ["--replications", "1"], ["--take-award", "yes"],
])
def test_bad_flags_exit_2_with_one_line(cli, flags):
    out = cli("solve", *flags)
    assert out.returncode == 2, out.stderr
    assert out.stderr.count("\n") == 1 and "Traceback" not in out.stderr and out.stdout == ""


def test_auto_decomposes_from_the_documented_scenario_count_at_each_resolution():
    for subperiods in (1, 6):
        n = auto_threshold(subperiods)
        assert resolve_method("auto", n - 1, subperiods) == "extensive"
        assert resolve_method("auto", n, subperiods) == "benders"
    assert auto_threshold(1) > auto_threshold(6) == auto_threshold(2)  # hourly, the extensive form goes further
    assert resolve_method("extensive", 100, 6) == "extensive" and resolve_method("benders", 1, 1) == "benders"
    with pytest.raises(ValueError, match="method must be one of"):
        resolve_method("simplex", 10, 6)


def test_unknown_command_exits_2(cli):
    out = cli("frobnicate")
    assert out.returncode == 2 and out.stderr.count("\n") == 1


def test_version_names_the_package_and_the_protocol(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    out = capsys.readouterr().out
    assert re.fullmatch(r"dmosim \S+ \(message schemas v(\d+); Python [^)]+\)\n", out), out
    assert f"message schemas v{SCHEMA_VERSION};" in out


def test_zenoh_flags_make_the_bus_config():
    parser = argparse.ArgumentParser()
    add_bus_flags(parser, "peer")
    args = parser.parse_args(["--mode", "router", "--listen", "tcp/127.0.0.1:0", "--lease", "2"])
    assert bus_config(args, "peer") == BusConfig(mode="router", listen=("tcp/127.0.0.1:0",), lease_s=2.0,
                                                 connect_timeout_s=60.0)
    args = parser.parse_args(["--connect", "tcp/127.0.0.1:7447", "--connect-timeout", "2.5"])
    config = bus_config(args, "client", "mg1")
    assert config.mode == "client" and json.loads(config.to_zenoh().get_json("connect/timeout_ms")) == 2500
    with pytest.raises(UsageError, match="lease_s"):
        bus_config(parser.parse_args(["--lease", "0"]), "peer")


def test_schemas_writes_one_json_schema_per_kind_and_an_index(tmp_path):
    assert main(["schemas", "--out", str(tmp_path / "schemas")]) == 0
    index = json.loads((tmp_path / "schemas" / "index.json").read_text())
    assert set(index["kinds"]) == set(KINDS) and index["phases"] == list(PHASES)
    report = MeterReport(sender="mg1", market_day="2026-07-01", hour=3, subperiods=2, p_m_mw=(1.0, 2.0),
                         deviation_mw=(0.0, 1.0))
    for kind, entry in index["kinds"].items():
        schema = json.loads((tmp_path / "schemas" / entry["file"]).read_text())
        jsonschema.Draft202012Validator.check_schema(schema)
        assert schema["$id"] == f"urn:dmosim:{kind}:v{index['schema_version']}"
    schema = json.loads((tmp_path / "schemas" / "meter_report.schema.json").read_text())
    jsonschema.validate(json.loads(encode(report)), schema)
    missing = {k: v for k, v in json.loads(encode(report)).items() if k != "subperiods"}
    with pytest.raises(jsonschema.ValidationError, match="subperiods"):
        jsonschema.validate(missing, schema)
    (tmp_path / "file").write_text("")
    assert main(["schemas", "--out", str(tmp_path / "file")]) == 2


def test_solve_evaluate_reports_the_estimate_and_refuses_too_few_scenarios(cli):
    out = cli("solve", "--subperiods", "1", "--scenarios", "2", "--evaluate", "6", "--json", "--workers", "1")
    assert out.returncode == 0, out.stderr
    evaluation = json.loads(out.stdout)["evaluation"]
    assert evaluation["scenarios"] == 6 and evaluation["low"] <= evaluation["expected_cost"] <= evaluation["high"]
    bad = cli("solve", "--subperiods", "1", "--scenarios", "2", "--evaluate", "1")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1
    assert "--evaluate: expected an integer in 2.." in bad.stderr


def test_info_prints_the_recorded_experiment_as_the_toml_of_its_run_directory(capsys):
    recording = Path(__file__).resolve().parents[1] / "data" / "schema-v2-two-days.mcap"
    assert main(["info", str(recording)]) == 0
    out = capsys.readouterr().out
    head, sep, block = out.partition("experiment (TOML")
    assert sep and "{'" not in out  # no Python dict anywhere
    toml = "\n".join(line.removeprefix("  ") for line in block.splitlines()[1:])
    assert tomllib.loads(toml)["market"]["penalty"] == 150.0 and tomllib.loads(toml)["days"] == 2
    from dmosim.experiment.spec import parse_experiment  # noqa: PLC0415
    from messages.recording import read_recording  # noqa: PLC0415

    config = json.loads(read_recording(recording).metadata["config"])
    assert parse_experiment(tomllib.loads(toml)) == parse_experiment(config)


def _flags_of(parser: argparse.ArgumentParser, prog: str):
    """(where, action) of every argument of ``parser`` and of its sub-verbs (``bench solver``...)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _flags_of(sub, f"{prog} {name}")
        elif not isinstance(action, argparse._HelpAction):
            yield prog, action


def _verb_parser(name: str) -> argparse.ArgumentParser:
    from dmosim.cli.main import build_parser  # noqa: PLC0415

    parser = build_parser(name)
    return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]


def test_every_flag_of_every_verb_has_help_text():
    from dmosim.cli.main import VERBS  # noqa: PLC0415

    bare = [f"{prog} {'/'.join(action.option_strings) or action.dest}" for name in VERBS
            for prog, action in _flags_of(_verb_parser(name), name)
            if not action.help or action.help == argparse.SUPPRESS]
    assert bare == []
    quiet = [prog for name in VERBS for prog, action in _flags_of(_verb_parser(name), name)
             if "--quiet" in action.option_strings]
    assert len(quiet) >= 6  # run, sweep, dmo, agent, record, router, replay: each checked above


@pytest.mark.parametrize("verb", ["info", "cat", "export", "plot", "replay", "settle"])
def test_the_verbs_that_read_run_directories_say_so(verb):
    path = next(a for a in _verb_parser(verb)._actions if a.dest == "path")
    said = "a recording, a run directory or a sweep directory" if verb == "settle" else "or a run directory"
    assert said in path.help


SHADOWED = ("{} shadows dmosim's package 'scenarios' (Python finds it first on sys.path: the current directory, "
            "with python -m, or PYTHONPATH); rename it, or run the installed dmosim command from another directory "
            "(README.md)")


def test_a_package_of_ours_found_elsewhere_first_on_the_path_is_named(tmp_path, monkeypatch):
    """Where Python would find a user's scenarios.py first, ``shadowing`` names it without importing it."""
    (tmp_path / "scenarios.py").write_text("raise SystemExit('the user file ran')\n")
    assert shadowing() is None
    monkeypatch.delitem(sys.modules, "scenarios")  # as in a fresh interpreter, which has not imported ours yet
    monkeypatch.syspath_prepend(tmp_path)
    assert shadowing() == SHADOWED.format(tmp_path / "scenarios.py")


@pytest.mark.slow
def test_a_scenarios_py_in_the_current_directory_is_named_not_imported(tmp_path):
    """python -m puts the current directory first on sys.path, where a user's scenarios.py would pass for ours: the
    executable refuses it before importing anything of its own (a fresh interpreter, so a process)."""
    (tmp_path / "scenarios.py").write_text("raise SystemExit('the user file ran')\n")
    env = {**os.environ, "PYTHONPATH": ""}
    done = subprocess.run([sys.executable, "-m", "dmosim", "--version"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == f"error: {SHADOWED.format(tmp_path / 'scenarios.py')}\n"



def test_run_from_a_recording_made_by_hand_without_its_experiment_says_what_is_missing(cli, tmp_path):
    """``dmosim record`` beside roles started by hand keeps no experiment unless one is attached: ``run --from`` says
    so in one line, exit 2, and repeats the recording once its experiment.toml is attached."""
    from dmosim.bench.recording import synthetic_day  # noqa: PLC0415
    from messages.keys import new_run_id  # noqa: PLC0415
    from messages.recording import RecordingWriter  # noqa: PLC0415
    from messages.recording.writer import read_attachments  # noqa: PLC0415

    def recording(name: str, attach=()) -> str:
        run_id = new_run_id()
        with RecordingWriter(tmp_path / name, run_id) as writer:
            writer.start({}, read_attachments(attach))
            for key, payload in synthetic_day(run_id, 1, 1)[:5]:
                writer.write(key, payload, 1_800_000_000_000_000_000)
        return str(tmp_path / name)

    said = cli("run", "--from", recording("by-hand.mcap"), "--check")
    assert said.returncode == 2 and said.stderr.count("\n") == 1
    assert "holds no experiment.toml" in said.stderr and "--attach experiment.toml" in said.stderr
    (tmp_path / "experiment.toml").write_text('seed = 4\n[agents]\ncount = 2\n')
    said = cli("run", "--from", recording("attached.mcap", [tmp_path / "experiment.toml"]), "--check")
    assert said.returncode == 0, said.stderr
