"""Smoke tests of the benchmarks (messaging, day, recovery): each runs end to end on tiny parameters and returns
the expected figures. No timing assertions: the figures themselves belong to the benchmark's output. The runs are
slow (those that start a run's processes or open Zenoh sessions, and the solver's and the clearing's, seconds of
solving); the arithmetic of the figures and the checks of the flags are the fast tier's."""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import pkgutil
import re
import tempfile
from pathlib import Path

import pytest

import dmosim.bench
from dmosim.bench import recovery
from dmosim.bench.day import agents_reported, run_and_read, split_day
from dmosim.bench.week import summarise
from dmosim.cli import main
from tests.dmosim.synthetic import realised_day, typed


def bench_json(capsys, *argv: str) -> dict:
    assert main(["bench", *argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_every_benchmark_module_is_a_bench_command(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    commands = set(re.search(r"\{([a-z,]+)\}", capsys.readouterr().out).group(1).split(","))
    assert commands == {m.name for m in pkgutil.iter_modules(dmosim.bench.__path__)}


@pytest.mark.slow  # Zenoh sessions
def test_messaging_runs_end_to_end(capsys):
    out = bench_json(capsys, "messaging", "--messages", "20", "--burst", "200", "--warmup", "5",
                     "--codec-iterations", "20")
    assert [row["kind"] for row in out["codec_us"]] == ["grid_state", "meter_report"]
    assert all(row["bytes"] > 0 and row["encode_us"] > 0 and row["decode_us"] > 0 for row in out["codec_us"])
    assert [row["path"] for row in out["round_trip_ms"]] == ["dmosim Bus", "plain zenoh"]
    for row in out["round_trip_ms"]:
        assert row["n"] == 20
        assert 0 < row["p50"] <= row["p90"] <= row["p99"] <= row["max"]
    for row in out["throughput"]:
        assert row["sent"] == 200 and 0 < row["received"] <= 200 and row["lost"] == 200 - row["received"]
        assert row["sent_per_s"] > 0 and row["received_per_s"] > 0
    assert out["ratios"]["round_trip_p50_bus_over_zenoh"] > 0
    assert out["goal"]["p50_round_trip_ms"] == out["round_trip_ms"][0]["p50"]


@pytest.mark.slow  # a market day's processes
def test_day_runs_end_to_end(capsys):
    out = bench_json(capsys, "day", "--agents", "1", "--scenarios", "1", "--gap", "0.05", "--timeout", "600")
    (row,) = out["days"]
    assert row["agents"] == 1 and row["incidents"] == 0
    assert row["day_s"] > 0 and row["compute_s"] > 0 and row["startup_s"] > 0 and row["agent_cpu_s"] > 0
    assert math.isclose(row["overhead_s"], row["day_s"] - row["compute_s"])
    assert row["process_s"] > row["day_s"]
    assert row["in_process_s"] > 0 and math.isclose(row["speedup"], row["process_s"] / row["in_process_s"])
    assert "notes" not in out  # the statements in one process are those of the processes
    assert [p["phase"] for p in out["phases"]] == ["bidding", "clearing", "scheduling", "realtime", "settlement"]
    assert math.isclose(sum(p["wall_s"] for p in out["phases"]), row["day_s"])
    assert out["goal"]["agents"] == 1 and out["goal"]["target_pct"] == 5.0


@pytest.mark.slow  # a market day's processes
def test_fleet_sums_every_process_of_the_run_and_resettles_its_recording(capsys):
    out = bench_json(capsys, "fleet", "--agents", "2", "--per-process", "2", "--timeout", "600")
    (row,) = out["fleets"]
    roles = ("agents_mib", "run", "dmo", "recorder", "host")  # both agents in one process forked from the host
    assert all(row[role] > 0 for role in roles) and row["agents"] == 2 and row["incidents"] == 0
    assert math.isclose(sum(row[role] for role in roles), row["total_gib"] * 1024, abs_tol=6)
    assert math.isclose(row["per_agent_mib"], row["total_gib"] * 1024 / 2, abs_tol=3)
    assert row["resettled_identically"] and 0 < row["solving_pct"] <= 100
    assert 0 < row["registration_s"] and 0 < row["clearing_s"] and row["day_s"] < row["wall_s"]
    assert out["goal"] == {}  # the goals are for a fleet of 200, judged on that fleet's row alone


@pytest.mark.slow
def test_recovery_loses_messages_everywhere_and_settles_every_statement_the_same(capsys, tmp_path):
    out = bench_json(capsys, "recovery", "--agents", "2", "--days", "1", "--scenarios", "1", "--subperiods", "1",
                     "--drop", "0.1", "--out", str(tmp_path))
    clean, dropped = out["runs"]
    assert (clean["run"], dropped["run"]) == ("fault-free", "dropped")
    assert clean["dropped_by_dmo"] == clean["dropped_by_agents"] == clean["sent_again"] == 0
    assert dropped["dropped_by_dmo"] + dropped["dropped_by_agents"] > 0 and dropped["sent_again"] > 0
    assert out["ratios"]["statement lines that differ"] == 0 and "differences" not in out
    assert out["ratios"]["wall dropped / fault-free"] > 0
    assert (tmp_path / "fault-free" / "recording.mcap").is_file() and (tmp_path / "dropped" / "result.json").is_file()


def test_split_takes_the_slowest_agent_per_step_and_bounds_cpu_by_the_cores():
    phase_s = {"registration": 2.0, "bidding": 3.0, "clearing": 0.1, "scheduling": 5.0, "realtime": 4.8,
               "settlement": 0.1}
    step = lambda kind, wall, cpu, hour=None: {"kind": kind, "hour": hour, "wall_s": wall, "cpu_s": cpu}  # noqa: E731
    hours = lambda wall, cpu: [step("grid_state", wall, cpu, h) for h in range(1, 25)]  # noqa: E731
    compute = {
        "mg1": [step("call_for_bids", 2.0, 1.0), step("award", 4.0, 2.0), *hours(0.1, 0.1),
                step("settlement_statement", 0.5, 0.5)],  # not a step the DMO waits for: ignored
        "mg2": [step("call_for_bids", 2.5, 2.0), step("award", 1.0, 1.0), *hours(0.15, 0.05)],
    }
    split = split_day(phase_s, compute, cores=2)
    phases = {row["phase"]: row for row in split["phases"]}
    assert "registration" not in phases
    assert phases["bidding"]["compute_s"] == 2.5 and phases["scheduling"]["compute_s"] == 4.0
    assert phases["realtime"]["compute_s"] == pytest.approx(24 * 0.15)
    assert phases["clearing"]["compute_s"] == 0 and phases["clearing"]["overhead_s"] == 0.1
    assert phases["bidding"]["cpu_bound_s"] == 2.0  # max(2.0, (1.0 + 2.0) / 2)
    assert phases["realtime"]["cpu_bound_s"] == pytest.approx(24 * 0.1)  # max(0.1, 0.15 / 2)
    t = split["totals"]
    assert t["startup_s"] == 2.0 and t["day_s"] == pytest.approx(13.0)
    assert t["compute_s"] == pytest.approx(2.5 + 4.0 + 3.6)
    assert t["overhead_s"] == pytest.approx(13.0 - 10.1)
    assert t["overhead_pct"] == pytest.approx(100 * 2.9 / 13.0)
    assert t["per_hour_ms"] == pytest.approx(1000 * (4.8 - 3.6) / 24)
    assert t["agent_cpu_s"] == pytest.approx(1.0 + 2.0 + 2.0 + 1.0 + 24 * 0.15)


def test_split_counts_as_computation_the_time_in_which_any_agent_computed_once_entries_say_when():
    """Two agents taking turns on one core: mg2 took the call for bids up late (0.5 s in) and waited for its turn
    until mg1 answered (1.0 s); the hour's grid states came 0.5 s apart and nobody computed in between."""
    t0 = 1_780_000_000 * 10**9
    at = lambda s: t0 + round(s * 1e9)  # noqa: E731
    def entry(kind, start, turn, wall, hour=None):
        return {"kind": kind, "hour": hour, "wall_s": wall, "cpu_s": 0.1, "started_at": at(start), "turn_s": turn}

    compute = {"mg1": [entry("call_for_bids", 0.0, 0.0, 1.0), entry("grid_state", 10.0, 0.0, 0.25, 1)],
               "mg2": [entry("call_for_bids", 0.5, 0.5, 1.5), entry("grid_state", 10.75, 0.0, 0.25, 2)]}
    phase_s = {"registration": 1.0, "bidding": 2.25, "realtime": 1.25}
    phases = {row["phase"]: row for row in split_day(phase_s, compute, cores=1)["phases"]}
    assert phases["bidding"]["compute_s"] == pytest.approx(2.0)  # mg1 0-1, mg2 1-2: the slowest agent's wall is 1.5
    assert phases["bidding"]["overhead_s"] == pytest.approx(0.25)
    assert phases["realtime"]["compute_s"] == pytest.approx(0.5)
    assert phases["realtime"]["overhead_s"] == pytest.approx(0.75)


def test_the_week_splits_each_day_by_its_own_compute_and_compares_the_last_day_with_the_first():
    phase_s = {"registration": 2.0, "bidding": 1.0, "clearing": 0.0, "scheduling": 2.0, "realtime": 2.4,
               "settlement": 0.0}
    day = lambda d: {"day": d, "market_day": f"2026-07-0{d}", "phase_s": phase_s, "incidents": []}  # noqa: E731
    entry = lambda d, kind, wall: {"kind": kind, "hour": None, "day": d, "wall_s": wall, "cpu_s": wall}  # noqa: E731
    compute = {"mg1": [entry(1, "call_for_bids", 0.5), entry(1, "award", 1.0), entry(2, "award", 1.8),
                       entry(3, "award", 1.2)]}
    memory = {"1": {"dmo": {"rss_mib": 90.0, "peak_mib": 100.0, "pss_mib": 60.0},
                    "mg1": {"rss_mib": 200.0, "peak_mib": 250.0, "pss_mib": None}},
              "2": {"dmo": {"rss_mib": 90.9, "peak_mib": 105.0, "pss_mib": 61.0},
                    "mg1": {"rss_mib": 200.5, "peak_mib": 250.0, "pss_mib": None}},
              "3": {"dmo": {"rss_mib": 91.8, "peak_mib": 110.0, "pss_mib": 61.2},
                    "mg1": {"rss_mib": 201.0, "peak_mib": 250.0, "pss_mib": None}}}
    result = typed({"agents": ["mg1"], "days": [day(1), day(2), day(3)], "memory_mib": memory,
                    "recorded": {"bytes": 30_000, "complete": True, "recorder": None}})
    report = summarise(result, compute, cores=2)
    assert [d["compute_s"] for d in report["days"]] == [1.5, 1.8, 1.2]  # each day its own entries only
    assert report["days"][0]["overhead_pct"] == pytest.approx(100 * (5.4 - 1.5) / 5.4, abs=0.01)
    assert {r["role"]: (r["rss_ratio"], r["peak_ratio"]) for r in report["memory"]} == {"dmo": (1.02, 1.1),
                                                                                        "mg1": (1.005, 1.0)}
    assert report["memory"][0]["pss_ratio"] == 1.02 and "pss_ratio" not in report["memory"][1]  # none: no smaps
    assert report["memory"][0]["rss_by_day_mib"] == [90.0, 90.9, 91.8]
    assert [r["rss_ratio_from_day_2"] for r in report["memory"]] == [1.01, 1.002]
    assert report["ratios"]["max rss_mib last / first day (any role)"] == 1.02
    assert report["ratios"]["max rss_mib last / second day (any role)"] == 1.01
    assert report["ratios"]["max peak_mib last / first day (any role)"] == 1.1
    assert report["ratios"]["recording bytes per agent-day"] == 10_000


def test_an_experiment_alone_is_split_over_all_its_days_and_run_as_processes_only(monkeypatch):
    """``bench day --agents --experiment FILE --no-in-process``: no fleet-size day, no day in one process, the
    experiment's phases summed over its days (a run of several has no ``phase_s`` of its own) and its solving share."""
    from dmosim.bench import day

    phase_s = {"registration": 3.0, "bidding": 1.0, "scheduling": 6.0, "realtime": 3.0}
    entry = lambda d, kind, at, wall: {"kind": kind, "hour": None, "day": d, "wall_s": wall, "cpu_s": wall,  # noqa: E731
                                       "started_at": int(at * 1e9), "turn_s": 0.0}
    days = [{"phase_s": phase_s, "market_day": "2026-07-01"},
            {"phase_s": {**phase_s, "registration": 0.0}, "market_day": "2026-07-02"}]
    result = typed({"days": days, "settlement": {},
                    "schedules_stopped_short": [{"agent": "mg1", "status": "time_limit", "mip_gap": 0.02}]})
    compute = {"mg1": [entry(1, "award", 100.0, 5.0), entry(2, "award", 200.0, 4.0)]}
    calls = []

    def fake(flags, timeout_s):
        calls.append(flags)
        return {"result": result, "compute": compute, "process_s": 30.0}

    monkeypatch.setattr(day, "run_and_read", fake)
    args = argparse.Namespace(agents=[], experiment=["x.toml"], in_process=False, timeout=60.0, scenarios=2,
                              subperiods=1, gap=0.01, time_limit=120.0)
    out = day.run(args)
    assert calls == [["x.toml"]] and out["days"] == [] and out["goal"] == {}
    (row,) = out["experiments"]
    assert row["day_s"] == 20.0 and row["startup_s"] == 3.0 and row["compute_s"] == 9.0
    assert row["solving_pct"] == pytest.approx(45.0) and row["stopped_short"] == 1 and "speedup" not in row
    assert {p["phase"]: p["wall_s"] for p in out["phases"]} == {"bidding": 2.0, "scheduling": 12.0, "realtime": 6.0}
    assert main(["bench", "day", "--agents"]) == 2  # nothing to run: one line, before anything starts


def test_compute_and_counts_come_from_the_agents_realised_days_in_the_result():
    """What the agents reported in their agent_day messages, as the DMO's result gives it: never a log line."""
    counts = lambda n: {"published": 9, "received": 9, "rejected": {}, "handler_errors": 0, "ignored": {},  # noqa: E731
                        "sent_again": n, "asked": 0, "faults_injected": {"drop": n}}
    entry = {"kind": "award", "hour": None, "wall_s": 0.5, "cpu_s": 0.4, "started_at": None, "turn_s": 0.0}
    realised = {"mg1": [realised_day(1, [entry], counts(1)), realised_day(2, [entry], counts(3))],
                "mg2": [realised_day(1, [], counts(0))]}
    compute, messages = agents_reported(typed({"agents": ["mg1", "mg2"], "realised": realised}))
    assert compute == {"mg1": [{**entry, "day": 1}, {**entry, "day": 2}], "mg2": []}
    assert messages["mg1"]["sent_again"] == 3 and messages["mg2"]["faults_injected"] == {"drop": 0}  # the last day's
    with pytest.raises(RuntimeError, match="no realised day from mg2"):
        agents_reported(typed({"agents": ["mg1", "mg2"], "realised": {**realised, "mg2": []}}))


@pytest.mark.slow  # a benchmark's run: every route, SCIP's included, on two seeds
def test_solver_bench_runs_every_route_on_every_seed_verifies_and_summarises_by_the_median(capsys):
    from dmosim.bench import solver
    from microgrid_agent.solvers.benders import ITERATIONS

    args = argparse.Namespace(scenarios=[1], subperiods=1, gap=0.01, cap=60.0, workers=1, seed=4, seeds=2, routes=None)
    result = solver.run(args)
    assert [(r["seed"], r["route"]) for r in result["rows"]] == [(s, r) for s in (4, 5) for r in solver.TIMED_ROUTES]
    assert all(r["verified"] for r in result["rows"]) and result["seeds"] == [4, 5]
    for seed in (4, 5):
        runs = {r["route"]: r for r in result["rows"] if r["seed"] == seed}
        for route in ("benders", "tree"):  # each decomposition's certified bound is below the others' schedules
            assert runs[route]["bound"] <= runs["extensive"]["objective"] * (1 + 1e-6)
        for r in runs.values():
            # the shares are parts of the wall time; what they leave out (the final dispatch at the best first
            # stage, the checker's call) is seconds on a shared machine, so no floor is asserted on them
            assert 0 < sum(r[k] for k in solver.SHARES) <= 1 + 1e-9 or r["route"] == "extensive"
            # the work beside the seconds: in all, and for a decomposition step by step in the trace
            assert r["simplex_iterations"] > 0 and r["nodes"] >= 0
            steps = [t for t in result["trace"] if (t["seed"], t["route"]) == (seed, r["route"])]
            assert sum(t["phase"] in ITERATIONS for t in steps) == r.get("iterations", 0)  # the extensive form: none
            for k in ("master_simplex_iterations", "master_nodes", "subproblems_simplex_iterations"):
                assert r.get(k, 0) == sum(t[k] for t in steps)
    lines = {line["route"]: line for line in result["summary"]}
    assert list(lines) == list(solver.TIMED_ROUTES) and lines["benders"]["over_benders"] == 1.0
    for route, line in lines.items():
        walls = sorted(r["wall_s"] for r in result["rows"] if r["route"] == route)
        assert line["seeds"] == line["solved"] == 2 and line["median_wall_s"] == pytest.approx(sum(walls) / 2)
        assert (line["min_wall_s"], line["max_wall_s"]) == (walls[0], walls[1])
    # A paper-size run takes hours: each solve announces itself and the decompositions report every iteration.
    lines = capsys.readouterr().err.splitlines()
    label = "dmosim: bench solver, 1 scenarios, seed 5: "
    benders, tree = lines.index(label + "benders"), lines.index(label + "tree")
    iterations = [ln for ln in lines[benders:tree] if ln.startswith(label + "benders ") and "iteration" in ln]
    benders_row = next(r for r in result["rows"] if r["seed"] == 5 and r["route"] == "benders")
    assert len(iterations) == benders_row["iterations"]
    assert any(ln.startswith(label + "tree: bound ") for ln in lines[tree:])
    assert lines.index(label + "extensive (cap 60 s)") > tree > benders


@pytest.mark.slow
def test_start_bench_solves_each_day_both_ways_from_the_day_befores_cold_schedule(capsys):
    assert main(["bench", "start", "--scenarios", "2", "--subperiods", "1", "--days", "3", "--gap", "0.01",
                 "--workers", "1", "--seed", "4", "--json"]) == 0
    printed = capsys.readouterr()
    out = json.loads(printed.out)
    assert [r["day"] for r in out["rows"]] == [1, 2, 3] and "started_s" not in out["rows"][0]
    for row in out["rows"][1:]:
        # to the same gap both ways; never worse than the start it took
        assert row["started_objective"] == pytest.approx(row["cold_objective"], rel=0.011)
        assert row["start_value"] is None or row["started_objective"] <= row["start_value"] * (1 + 1e-9)
        assert row["started_over_cold"] == pytest.approx(row["started_s"] / row["cold_s"])
    summary = out["summary"]
    assert summary["days started"] == 2 and summary["verified"]
    assert summary["seconds saved in all"] == pytest.approx(sum(r["cold_s"] - r["started_s"] for r in out["rows"][1:]))
    # the two ways alternate their order, so that neither always runs second
    lines = printed.err.splitlines()
    said = [ln.rsplit(": ", 1)[1] for ln in lines if re.fullmatch(r"dmosim: bench start, day \d of 3: \w+", ln)]
    numbers = [(m[1], int(m[2])) for ln in lines if (m := re.search(r": started: benders (.+) (\d+): bound", ln))]
    at = next(i for i, (what, _) in enumerate(numbers) if what == "start after iteration")  # and every iteration
    assert numbers[at + 1] == ("integer master, iteration", numbers[at][1] + 1)  # the start is not an iteration
    assert said == ["cold", "started", "cold", "cold", "started"]


def test_solver_bench_refuses_a_route_this_installation_lacks(monkeypatch):
    from dmosim.bench import solver
    from dmosim.console import UsageError

    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pyscipopt" else object())
    assert solver.routes_of(None) == ["benders", "extensive"]
    with pytest.raises(UsageError, match="^--routes: method tree needs PySCIPOpt, which is not installed: pip install"):
        solver.routes_of(["benders", "tree"])


@pytest.mark.slow  # a benchmark's run: the copper plate and two feeders, each cleared twice
def test_clearing_runs_end_to_end(capsys):
    out = bench_json(capsys, "clearing", "--agents", "4", "--repeats", "2", "--buses", "60")
    assert out["agents"] == 4 and out["steps"] == 4 * 24 * 3 and out["repeats"] == 2
    assert [row["case"] for row in out["rows"]] == ["copper plate", "ieee33", "synthetic60"]
    for row in out["rows"]:
        assert 0 < row["min_s"] <= row["median_s"] <= row["max_s"]
        assert sum(row[f"hours_{label}"] for label in ("none", "import", "export", "line", "voltage")) == 24
    assert out["rows"][0]["over_copper_plate"] == 1.0
    assert [row["case"] for row in out["ac_faithful"]] == ["ieee33", "synthetic60"]
    for row in out["ac_faithful"]:
        assert row["over_one_shot"] == pytest.approx(row["median_s"] / row["one_shot_median_s"])
        assert 1 <= row["iterations_mean"] <= row["iterations_max"] <= 20
        assert row["ac_hours_broken"] <= row["one_shot_hours_broken"] and row["loss_price_mean"] > 0
    assert out["goal"] == {}  # the goals are for 100 agents


@pytest.mark.slow  # a real dmosim run, stopped
def test_a_run_that_outlasts_its_timeout_is_stopped_and_its_directory_named(tmp_path):
    with pytest.raises(RuntimeError, match=r"took over 0\.5 s and was stopped \(run directory: .*/run\)$"):
        run_and_read(["--agents", "1"], timeout_s=0.5, keep=tmp_path / "run")


@pytest.mark.slow  # a real dmosim run, refused
def test_recovery_keeps_the_scratch_directory_of_a_run_that_failed_and_names_it(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # where the scratch directory goes
    parser = argparse.ArgumentParser()
    recovery.add_arguments(parser)
    args = parser.parse_args([])
    args.scenarios = 0  # refused by dmosim run (exit 2): the first run fails
    with pytest.raises(RuntimeError, match=r"exited 2: .*--scenarios.*\(run directory: (.*/fault-free)\)") as failed:
        recovery.run(args)
    root = Path(re.search(r"\(run directory: (.*)\)", str(failed.value)).group(1)).parent
    assert root.parent == tmp_path and root.is_dir()  # kept: the runs the error names are in it


@pytest.mark.slow  # a real dmosim run, refused
def test_a_run_that_fails_is_named_by_its_one_line_failure_from_its_start_to_its_end(tmp_path):
    far = tmp_path.joinpath(*["d" * 150] * 4) / "none.toml"  # a fleet file whose name makes that line long
    with pytest.raises(RuntimeError) as failed:
        run_and_read(["--fleet", str(far)], timeout_s=120, keep=tmp_path / "run")
    said = str(failed.value)
    cut = r" exited 2: error: fleet file not found: .{200,} \.\.\. .*/none\.toml \(run directory: "
    assert re.search(cut, said), said
