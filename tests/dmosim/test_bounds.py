"""Every size a user can set has an upper bound: docs/experiments.md's table of bounds and the constants agree, every
bound constant is in the table, and each bound is enforced at the boundary, by the experiment file and by the
flags of every verb that takes it (one line, exit 2, before anything starts)."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

from dmosim.cli import main
from dmosim.experiment.spec import (MAX_FAULT_SPEC, MAX_FAULTS, MAX_NAME, MAX_PATH, MAX_PROFILE_DAYS, MAX_RULE,
                                 MAX_SECONDS, MAX_WORKERS, Experiment, ExperimentError, parse_experiment)
from dmosim.experiment.sweep import MAX_VARIANTS, parse_setting, variants
from dmo.market.rules import MAX_MW, MAX_RATE
from messages.schemas import MAX_AGENTS, MAX_DAYS, MAX_SUBPERIODS
from scenarios.days import MAX_SEED
from scenarios.fleet import MAX_SCALE
from scenarios.generation import MAX_SAMPLE, MAX_SCENARIOS

ROOT = Path(__file__).resolve().parents[2]
# The modules that define bounds of settings; each MAX_ constant they define must be in the table.
BOUND_MODULES = ("scenarios/case.py", "scenarios/days.py", "scenarios/fleet.py", "scenarios/generation.py",
                 "scenarios/network.py", "scenarios/pandapower_json.py",
                 "dmosim/experiment/spec.py", "dmosim/experiment/sweep.py", "dmosim/cli/solve.py", "dmo/market/rules.py",
                 "messages/transport/credentials.py")


def table() -> list[dict[str, str]]:
    doc = (ROOT / "docs" / "experiments.md").read_text()
    section = doc.split("\n## Bounds\n", 1)[1].split("\n## ", 1)[0]
    lines = [ln for ln in section.splitlines() if ln.startswith("|")]
    head = [c.strip() for c in lines[0].strip("|").split("|")]
    return [dict(zip(head, (c.strip() for c in ln.strip("|").split("|")))) for ln in lines[2:]]


def resolve(dotted: str):
    module, name = dotted.rsplit(".", 1)
    return getattr(importlib.import_module(module), name)


def test_the_table_of_bounds_and_the_code_agree():
    rows = table()
    assert len(rows) >= 20
    for row in rows:
        constants = re.findall(r"`([\w.]+\.MAX_\w+)`", row["constant"])
        bound = float(re.match(r"[\d,.]+", row["at most"]).group(0).replace(",", ""))
        assert constants, row
        for constant in constants:
            assert resolve(constant) == bound, f"{constant} is {resolve(constant)}, the table says {row['at most']}"


def test_every_bound_the_code_defines_is_in_the_table():
    documented = {c for row in table() for c in re.findall(r"`([\w.]+\.MAX_\w+)`", row["constant"])}
    defined = set()
    for path in BOUND_MODULES:
        module = path.removesuffix(".py").replace("/", ".")
        for node in ast.parse((ROOT / path).read_text()).body:
            if isinstance(node, ast.Assign):
                defined |= {f"{module}.{t.id}" for t in node.targets
                            if isinstance(t, ast.Name) and t.id.startswith("MAX_")}
    assert defined - documented == set(), "bounds missing from docs/experiments.md"


# --- the experiment file ---------------------------------------------------------------------------------------

FAULT = "drop:dmo/clock:0.1"
RULE = "deadband:rate=" + "0" * (MAX_RULE - len("deadband:rate=") - 3) + "150"  # 150, written MAX_RULE long


@pytest.mark.parametrize("at, over", [
    ({"agents": {"count": MAX_AGENTS}}, {"agents": {"count": MAX_AGENTS + 1}}),
    ({"agents": {"generate": MAX_AGENTS}}, {"agents": {"generate": MAX_AGENTS + 1}}),
    ({"days": MAX_DAYS}, {"days": MAX_DAYS + 1}),
    ({"market_day": "9999-12-30", "days": 2}, {"market_day": "9999-12-31", "days": 2}),
    ({"schedule": {"scenarios": MAX_SCENARIOS}}, {"schedule": {"scenarios": MAX_SCENARIOS + 1}}),
    ({"schedule": {"workers": MAX_WORKERS}}, {"schedule": {"workers": MAX_WORKERS + 1}}),
    ({"market": {"subperiods": MAX_SUBPERIODS}}, {"market": {"subperiods": MAX_SUBPERIODS + 1}}),
    ({"seed": MAX_SEED}, {"seed": MAX_SEED + 1}),
    ({"seed": 0}, {"seed": -1}),
    ({"deadlines": {"hour": MAX_SECONDS}}, {"deadlines": {"hour": MAX_SECONDS + 0.5}}),
    ({"schedule": {"time_limit": MAX_SECONDS}}, {"schedule": {"time_limit": MAX_SECONDS + 0.5}}),
    ({"profiles": {"load_scale": [MAX_SCALE]}}, {"profiles": {"load_scale": [MAX_SCALE + 0.5]}}),
    ({"profiles": {"renewable_scale": [1.0] * MAX_PROFILE_DAYS}},
     {"profiles": {"renewable_scale": [1.0] * (MAX_PROFILE_DAYS + 1)}}),
    ({"market": {"penalty": MAX_RATE}}, {"market": {"penalty": MAX_RATE + 1}}),
    ({"market": {"credit": MAX_RATE}}, {"market": {"credit": MAX_RATE + 1}}),
    ({"market": {"import_limit": MAX_MW}}, {"market": {"import_limit": MAX_MW + 1}}),
    ({"faults": [FAULT] * MAX_FAULTS}, {"faults": [FAULT] * (MAX_FAULTS + 1)}),
    ({"faults": [FAULT.ljust(MAX_FAULT_SPEC, "0")]}, {"faults": [FAULT.ljust(MAX_FAULT_SPEC + 1, "0")]}),
    ({"name": "n" * MAX_NAME}, {"name": "n" * (MAX_NAME + 1)}),
    ({"market": {"case": "c" * MAX_PATH}}, {"market": {"case": "c" * (MAX_PATH + 1)}}),
    ({"market": {"settlement": RULE}}, {"market": {"settlement": RULE + "0"}}),
])
def test_an_experiment_at_a_bound_is_valid_and_past_it_is_refused(at, over):
    parse_experiment(at)
    with pytest.raises(ExperimentError) as err:
        parse_experiment(over, "exp.toml")
    assert str(err.value).startswith("exp.toml: ") and "\n" not in str(err.value)


# --- sweeps --------------------------------------------------------------------------------------------------------

def test_a_sweep_counts_its_runs_before_making_any():
    seeds = parse_setting("seed=" + ",".join(map(str, range(MAX_VARIANTS // 10))))
    ten = parse_setting("market.penalty=" + ",".join(str(10 * i) for i in range(10)))
    assert len(variants(Experiment(), [seeds, ten])) == MAX_VARIANTS
    eleven = parse_setting("market.penalty=" + ",".join(str(10 * i) for i in range(11)))
    with pytest.raises(ExperimentError, match=f"1,100 runs; a sweep has at most {MAX_VARIANTS}"):
        variants(Experiment(), [seeds, eleven])
    huge = [parse_setting("seed=" + ",".join(map(str, range(1000))))] * 1  # a billion combinations, never made
    keys = [("seed", huge[0][1]), ("market.penalty", huge[0][1]), ("market.credit", huge[0][1])]
    with pytest.raises(ExperimentError, match="1,000,000,000 runs"):
        variants(Experiment(), keys)
    with pytest.raises(ExperimentError, match=f"{MAX_VARIANTS + 1} values"):
        parse_setting("seed=" + ",".join(map(str, range(MAX_VARIANTS + 1))))


# --- the flags of every verb ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("argv, flag", [
    (["run", "--agents", str(MAX_AGENTS + 1), "--check"], "--agents"),
    (["run", "--days", str(MAX_DAYS + 1), "--check"], "--days"),
    (["run", "--generate", str(MAX_AGENTS + 1), "--check"], "--generate"),
    (["fleet", "--agents", str(MAX_AGENTS + 1)], "--agents"),
    (["run", "--scenarios", str(MAX_SCENARIOS + 1), "--check"], "--scenarios"),
    (["run", "--workers", str(MAX_WORKERS + 1), "--check"], "--workers"),
    (["run", "--subperiods", str(MAX_SUBPERIODS + 1), "--check"], "--subperiods"),
    (["run", "--seed", "-1", "--check"], "--seed"),
    (["run", "--seed", str(MAX_SEED + 1), "--check"], "--seed"),
    (["run", "--seed", "9" * 5000, "--check"], "--seed"),
    (["run", "--hour-timeout", "86401", "--check"], "--hour-timeout"),
    (["run", "--time-limit", "0", "--check"], "--time-limit"),
    (["run", "--load-scale", "1,11", "--check"], "--load-scale"),
    (["run", "--load-scale", ",".join(["1"] * (MAX_PROFILE_DAYS + 1)), "--check"], "--load-scale"),
    (["run", "--penalty", "1e7", "--check"], "--penalty"),
    (["run", "--import-limit", "1e7", "--check"], "--import-limit"),
    (["run", "--market-day", "9999-12-31", "--days", "2", "--check"], "market_day"),
    (["run", "--agents", "2", "--fleet", "fleet.toml", "--check"], "--agents and a fleet"),
    (["run", *[f for _ in range(MAX_FAULTS + 1) for f in ("--fault", FAULT)], "--check"], "faults"),
    (["dmo", "--agents", str(MAX_AGENTS + 1)], "--agents"),
    (["dmo", "--agents", "1", "--days", str(MAX_DAYS + 1)], "--days"),
    (["dmo", "--agents", "1", "--market-day", "9999-12-31", "--days", "2", "--insecure"], "market_day"),
    (["dmo", "--agents", "1", "--subperiods", str(MAX_SUBPERIODS + 1)], "--subperiods"),
    (["dmo", "--agents", "1", "--seed", "-1"], "--seed"),
    (["dmo", "--agents", "1", "--bid-timeout", "1e9"], "--bid-timeout"),
    (["dmo", "--agents", "1", "--await-recorder", "1e9"], "--await-recorder"),
    (["dmo", "--agents", "1", "--fault-seed", "-1"], "--fault-seed"),
    (["dmo", "--agents", "1", "--penalty", "1e7"], "--penalty"),
    (["dmo", "--agents", "1", *[f for _ in range(MAX_FAULTS + 1) for f in ("--fault", FAULT)], "--insecure"],
     "--fault"),
    (["dmo", "--experiment", "no-such-experiment.toml"], "no-such-experiment.toml"),
    (["agent", "--id", "mg7", "--run-id", "20261124T093000-3fa2c1"], "mg7 is not an agent of the experiment"),
    (["agent", "--id", "mg1", "--scenarios", str(MAX_SCENARIOS + 1)], "--scenarios"),
    (["agent", "--id", "mg1", "--workers", str(MAX_WORKERS + 1)], "--workers"),
    (["agent", "--id", "mg1", "--scale", "11"], "--scale"),
    (["agent", "--id", "mg1", "--shift-hours", "24"], "--shift-hours"),
    (["agent", "--id", "mg1", "--seed", str(MAX_SEED + 1)], "--seed"),
    (["agent", "--id", "mg1", "--idle-timeout", "1e9"], "--idle-timeout"),
    (["agent", "--id", "mg1", "--renewable-scale", "0"], "--renewable-scale"),
    (["router", "--agents", str(MAX_AGENTS + 1)], "--agents"),
    (["router", "--agents", "2", "--fleet", "fleet.toml"], "--agents and --fleet"),
    (["credentials", "--out", "x", "--agents", str(MAX_AGENTS + 1)], "--agents"),
    (["credentials", "--out", "x", "--days", "367"], "--days"),
    (["credentials", "--out", "x", *[f for i in range(17) for f in ("--reader", f"r{i}")]], "at most 16 readers"),
    (["solve", "--scenarios", str(MAX_SCENARIOS + 1)], "--scenarios"),
    (["solve", "--sample-size", str(MAX_SAMPLE + 1)], "--sample-size"),
    (["solve", "--scenarios", "3", "--sample-size", "2"], "--sample-size 2"),
    (["solve", "--evaluate", str(MAX_SAMPLE + 1)], "--evaluate"),
    (["solve", "--replications", "101"], "--replications"),
    (["solve", "--subperiods", str(MAX_SUBPERIODS + 1)], "--subperiods"),
    (["solve", "--seed", "-1"], "--seed"),
    (["solve", "--workers", str(MAX_WORKERS + 1)], "--workers"),
    (["solve", "--transfer-scale", "11"], "--transfer-scale"),
    (["solve", "--penalty", "1e7"], "--penalty"),
    (["solve", "--time-limit", "1e9"], "--time-limit"),
    (["study", "table2", "--scenarios", str(MAX_SCENARIOS + 1)], "--scenarios"),
    (["study", "table2", "--scenarios", "3", "--sample-size", "2"], "--sample-size 2"),
    (["sweep", "exp.toml", "--set", "seed=1", "--parallel", str(MAX_VARIANTS + 1)], "--parallel"),
    (["sweep", "exp.toml", "--set", f"schedule.workers={MAX_WORKERS + 1}"], "schedule.workers"),
    (["sweep", "exp.toml", "--set", f"seed=1,{MAX_SEED + 1}"], "seed"),
])
def test_a_flag_past_its_bound_is_one_line_and_exit_2_before_anything_starts(argv, flag, tmp_path, monkeypatch,
                                                                             capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "exp.toml").write_text("[agents]\ncount = 1\n")
    (tmp_path / "fleet.toml").write_text('[[agents]]\nid = "mg1"\n')
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert flag in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["exp.toml", "fleet.toml"]  # nothing made
