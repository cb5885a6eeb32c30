"""A run never ends quietly wrong: the verdict on a run's result (``dmosim.results.verdict``), read on synthetic result
dicts; a sweep's rows of an untrusted run; the DMO's journal read as a recording; and ``dmosim info``'s count of
the meter data the DMO did not have."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dmosim.bench.recording import synthetic_day
from dmosim.cli.info import describe, missing_meter, render
from dmosim.cli.main import main
from dmo.operator.journal import traffic_entry
from dmosim.experiment.spec import Experiment
from dmosim.launch.local import resettled
from dmosim.results.journaled import journal_recording
from dmosim.results.sweeps import sweep_rows
from dmosim.results.tables import tables
from dmosim.results.verdict import SHOWN_PROBLEMS, one_line, problems, verdict
from messages import decode
from messages.keys import new_run_id
from messages.recording import RecordingWriter, read_recording
from tests.dmosim.synthetic import typed

ROOT = Path(__file__).resolve().parents[2]
DAY, NEXT = "2026-07-01", "2026-07-02"


def day(n: int, market_day: str, agents=("mg1", "mg2"), **extra) -> dict:
    return {"day": n, "market_day": market_day, "settlement": {a: {"total": 100.0} for a in agents}, **extra}


def result(*days: dict, agents=("mg1", "mg2"), **extra) -> dict:
    return {"agents": list(agents), "days": list(days), **extra}


def judged(res: dict, **given) -> list[str]:
    """The verdict's problems with a synthetic result, its recording and reproduction as the run's result says."""
    report = typed(res)
    return problems(report, recording=report.recorded, reproduced=report.reproduced, **given)


def recorded_all(res: dict) -> set[tuple[str, str]]:
    return {(d["market_day"], a) for d in res["days"] for a in d["settlement"]}


# --- the verdict -----------------------------------------------------------------------------------------------

def test_a_clean_run_has_no_problem_and_a_missing_locked_out_field_counts_as_empty():
    res = result(day(1, DAY), day(2, NEXT, locked_out=[]), recorded={"complete": True, "recorder": None},
                 reproduced={"source": "a.mcap", "identical": True, "differences": []})
    assert judged(res, agents=["mg1", "mg2"], days=2, recorded=recorded_all(res)) == []
    assert verdict([]).model_dump() == {"ok": True, "problems": []}


def test_an_agent_locked_out_on_a_day_is_a_problem_naming_it_and_the_day():
    res = result(day(1, DAY), day(2, NEXT, locked_out=["mg2"]))
    found = judged(res, agents=["mg1", "mg2"], days=2)
    assert found == [f"mg2 was locked out on {NEXT}: its process talked to the DMO while the DMO was not taking its "
                     "messages"]
    assert verdict(found).ok is False


def test_a_day_not_settled_and_agents_without_a_statement_are_problems():
    res = result(day(1, DAY, agents=("mg1",)))  # mg2 registered, but has no statement; day 2 never came
    assert judged(res, agents=["mg1", "mg2", "mg3"], days=2) == [
        "day 2 of 2 was not settled", f"mg2 has no statement for {DAY}", f"mg3 has no statement for {DAY}"]


def test_a_complete_recording_must_hold_every_statement_the_dmo_settled():
    res = result(day(1, DAY), day(2, NEXT))
    held = recorded_all(res) - {(NEXT, "mg1")}
    assert judged(res, agents=["mg1", "mg2"], days=2, recorded=held) == [
        f"the recording lacks mg1's statement for {NEXT}"]
    assert judged(res, agents=["mg1", "mg2"], days=2, recorded=None) == []  # incomplete: nothing asked of it


@pytest.mark.parametrize("recorded, expected", [
    ({"complete": False, "recorder": "killed at day 1 realtime hour 8 (--fault kill:recorder:8)"},
     "the recorder failed: killed at day 1 realtime hour 8 (--fault kill:recorder:8); the recording is incomplete"),
    ({"complete": False, "recorder": None, "error": "r.mcap: not an MCAP file"},
     "the recording cannot be read: r.mcap: not an MCAP file"),
    ({"complete": False, "recorder": None, "messages": 3}, "the recording is incomplete"),
])
def test_a_failed_recorder_or_a_bad_recording_is_a_problem(recorded, expected):
    assert judged(result(day(1, DAY), recorded=recorded), agents=["mg1", "mg2"], days=1) == [expected]


@pytest.mark.parametrize("resettled, expected", [
    ({"identical": True, "differences": []}, []),
    ({"identical": False, "differences": [f"{DAY}: mg1 total: recorded 10.0, recomputed 12.5", "more"]},
     [f"the recording does not re-settle as the DMO settled: 2 difference(s), first {DAY}: mg1 total: recorded "
      "10.0, recomputed 12.5"]),
    ({"identical": False, "error": "the recording names the rule evil.py:rule, not the experiment's"},
     ["the recording cannot be re-settled: the recording names the rule evil.py:rule, not the experiment's"]),
])
def test_a_complete_recording_that_does_not_resettle_to_the_published_statements_is_a_problem(resettled, expected):
    recorded = {"complete": True, "recorder": None, "resettled": resettled}
    assert judged(result(day(1, DAY), recorded=recorded), agents=["mg1", "mg2"], days=1) == expected


def test_the_run_resettles_its_recording_and_finds_a_meter_report_the_recording_lost(tmp_path):
    """As dmosim run does before its verdict (``launch.local.resettled``): a whole recorded day re-settles to its
    statements; one that lost an hour of mg2's meter reports does not, and the difference names mg2."""
    run_id = new_run_id()
    whole = synthetic_day(run_id, 2, 2)
    experiment = Experiment()
    rec = read_recording(write(tmp_path / "whole.mcap", run_id, whole))
    assert resettled(rec, [DAY], experiment).model_dump() == {"identical": True, "differences": []}
    lost = [m for m in whole if not (m[0].endswith("agent/mg2/meter") and decode(m[1]).hour == 3)]
    again = resettled(read_recording(write(tmp_path / "lost.mcap", run_id, lost)), [DAY], experiment)
    assert again.identical is False and again.differences
    assert all(d.startswith(f"{DAY}: mg2 ") for d in again.differences), again.differences
    found = judged(result(day(1, DAY), recorded={"complete": True, "recorder": None, "resettled": again}),
                     agents=["mg1", "mg2"], days=1)
    assert len(found) == 1 and found[0].startswith("the recording does not re-settle as the DMO settled")


def test_a_from_run_that_did_not_reproduce_is_a_problem_with_its_first_difference():
    diffs = [f"mg1 {DAY} hour 5: total 1385.1 then, 185.1 now", f"mg1 {DAY} hour 6: total 1418.0 then, 218.0 now"]
    res = result(day(1, DAY), reproduced={"source": "a.mcap", "identical": False, "differences": diffs})
    assert judged(res, agents=["mg1", "mg2"], days=1) == [
        f"--from a.mcap: 2 statement line(s) differ from the recording, first {diffs[0]}"]
    unreadable = result(day(1, DAY), reproduced={"source": "a.mcap", "identical": False, "differences": [],
                                                 "error": "a.mcap: no such file"})
    assert judged(unreadable, agents=["mg1", "mg2"], days=1) == ["--from a.mcap: cannot compare: a.mcap: no such file"]


def test_the_one_line_names_the_first_problems_and_counts_the_rest():
    found = [f"problem {i}" for i in range(SHOWN_PROBLEMS + 2)]
    line = one_line(found)
    assert "\n" not in line and line.startswith("the run is not to be trusted: problem 0; problem 1")
    assert f"problem {SHOWN_PROBLEMS - 1}; and 2 more" in line and f"problem {SHOWN_PROBLEMS}" not in line
    assert one_line(["only this"]) == "the run is not to be trusted: only this"
    words = {3: "three"}[SHOWN_PROBLEMS]  # docs/experiments.md says how many the line names
    assert f"the first {words} problems" in (ROOT / "docs" / "experiments.md").read_text().replace("\n", " ")


# --- a sweep's rows --------------------------------------------------------------------------------------------

def test_a_sweep_tables_an_untrusted_run_with_its_money_and_its_problems():
    settled = {"mg1": {"total": 10.0, "energy_charge": 10.0}}
    ok = sweep_rows({"seed": 1}, "seed=1", "r1", 3.0, typed({"settlement": settled, "verdict": verdict([])}))
    bad = sweep_rows({"seed": 2}, "seed=2", "r2", 3.0, typed({"settlement": settled, "verdict": verdict(["a", "b"])}),
                     "failed: the run is not to be trusted: a; b")
    failed = sweep_rows({"seed": 3}, "seed=3", "r3", 3.0, None, "failed: mg1 failed")
    assert [(r["status"], r["total"], r["error"]) for r in ok + bad + failed] == [
        ("ok", 10.0, None), ("untrusted", 10.0, "a; b"), ("failed", None, "failed: mg1 failed")]


def test_a_sweep_of_seeds_gives_per_setting_the_mean_and_95_percent_interval_of_each_figure(tmp_path):
    import pandas as pd  # noqa: PLC0415

    from dmosim.results.sweeps import seed_summary, sweep_figure  # noqa: PLC0415
    from dmosim.studies.figures import save  # noqa: PLC0415

    rows = []
    for penalty in (100, 300):
        for seed, total in ((1, 9.0), (2, 10.0), (3, 11.0)):
            settled = {"mg1": {"total": penalty + total, "deviation_mwh": 1.0}, "mg2": {"total": 5.0}}
            rows += sweep_rows({"market.penalty": penalty, "seed": seed}, f"{penalty}-{seed}", "r", 1.0,
                               typed({"settlement": settled, "verdict": verdict([])}))
    rows += sweep_rows({"market.penalty": 100, "seed": 4}, "100-4", "r", 1.0, None, "failed: mg1 failed")
    table = pd.DataFrame(rows)
    summary = seed_summary(table, ["market.penalty", "seed"]).set_index(["market.penalty", "agent"])
    mg1 = summary.loc[(100, "mg1")]
    half = 4.302652729911275 / 3 ** 0.5  # t(0.975, 2 degrees of freedom) x sd 1 / sqrt(3 seeds)
    assert mg1["runs"] == 3 and mg1["total_mean"] == 110.0  # the failed seed 4 counts for nothing
    assert abs(mg1["total_low"] - (110.0 - half)) < 1e-9 and abs(mg1["total_high"] - (110.0 + half)) < 1e-9
    assert summary.loc[(300, "mg2"), ["total_low", "total_mean", "total_high"]].tolist() == [5.0, 5.0, 5.0]
    assert "seed" not in summary.reset_index() and summary.loc[(300, "mg1"), "deviation_mwh_mean"] == 1.0
    for keys in (["market.penalty", "seed"], ["seed"]):
        figure = sweep_figure(table if "market.penalty" in keys else table[table["market.penalty"] == 100], keys)
        bars = [c for ax in figure.axes for c in ax.containers if getattr(c, "has_yerr", False)]
        assert len(bars) == 2 * 2, keys  # an interval per agent, of the bill and of the penalty
        assert save(figure, tmp_path / "sweep.png").stat().st_size > 10_000


# --- the DMO's journal as a recording ----------------------------------------------------------------------------

def test_the_journal_read_as_a_recording_gives_the_tables_the_recording_gives(tmp_path):
    run_id = new_run_id()
    traffic = synthetic_day(run_id, 2, 2)
    key, good = next((k, p) for k, p in traffic if k.endswith("agent/mg1/meter"))
    traffic.insert(5, (key, good[:-9]))  # a payload cut short: invalid, as the recorder would file it
    times = [1_800_000_000_000_000_000 + i * 1_000_000 for i in range(len(traffic))]
    journal = tmp_path / "dmo.journal"
    lines = [{"journal": 1, "run_id": run_id, "market_day": DAY}, {"clock": "registration", "hour": None}]
    lines += [traffic_entry(k, p, t) for (k, p), t in zip(traffic, times)]
    journal.write_text("".join(json.dumps(line) + "\n" for line in lines) + '{"traffic": "cut by a kill')
    with RecordingWriter(tmp_path / "day.mcap", run_id) as writer:
        writer.start({"market_day": DAY, "agents": "mg1,mg2"})
        for (k, p), t in zip(traffic, times):
            writer.write(k, p, t)
    recorded = read_recording(tmp_path / "day.mcap")
    journaled = journal_recording(journal, run_id, {"market_day": DAY, "days": "1", "agents": "mg1,mg2"})
    assert [(m.key, m.payload, m.log_time, m.invalid is None) for m in journaled.messages] == [
        (m.key, m.payload, m.log_time, m.invalid is None) for m in recorded.messages]
    assert sum(m.invalid is not None for m in journaled.messages) == 1
    ours, theirs = tables(journaled), tables(recorded)
    for name, frame in ours.items():
        assert frame.equals(theirs[name]), name
    assert len(ours["hours"]) == 48


# --- dmosim info: the meter data the DMO did not have ------------------------------------------------------------

def write(path: Path, run_id: str, messages) -> Path:
    with RecordingWriter(path, run_id) as writer:
        writer.start({"market_day": DAY, "agents": "mg1,mg2"})
        for i, (key, payload) in enumerate(messages):
            writer.write(key, payload, 1_800_000_000_000_000_000 + i * 1_000_000)
    return path


def test_info_counts_hours_without_a_meter_report_when_no_statement_says_so(tmp_path):
    run_id = new_run_id()
    whole = synthetic_day(run_id, 2, 2)
    rec = read_recording(write(tmp_path / "whole.mcap", run_id, whole))
    assert missing_meter(rec) == [] and "missing:     nothing" in render(describe(rec))

    def dropped(key, payload) -> bool:
        return "/statement/" in key or key.endswith("agent/mg2/meter") and decode(payload).hour in (3, 4)

    rec = read_recording(write(tmp_path / "cut.mcap", run_id, [m for m in whole if not dropped(*m)]))
    assert missing_meter(rec) == [{"market_day": DAY, "agent": "mg2", "hours": [3, 4], "subperiods": [2, 2],
                                   "penalty": None, "settled": False}]
    text = render(describe(rec))
    assert f"missing:     mg2 {DAY}: no accepted meter report for hour(s) 3-4 (4 sub-period(s)); no statement" in text
    assert "missing:     nothing" not in text


def test_info_does_not_count_a_report_the_recording_lacks_but_the_statement_settled_as_metered(tmp_path):
    run_id = new_run_id()
    messages = [(k, p) for k, p in synthetic_day(run_id, 2, 2)
                if not (k.endswith("agent/mg1/meter") and decode(p).hour == 9)]
    rec = read_recording(write(tmp_path / "day.mcap", run_id, messages))
    assert missing_meter(rec) == []  # the DMO had it: a gap of the recording, not of the meter data
    assert any("no meter report recorded for hour(s) 9" in gap for gap in describe(rec)["missing"])


# --- the recorder's fault, checked before anything runs ----------------------------------------------------------

@pytest.mark.parametrize("argv, says", [
    (["run", "--fault", "restart:recorder:3", "--check"], "the recorder can only be killed"),
    (["run", "--fault", "kill:recorder:3", "--no-record", "--check"], "there is no recorder to kill with --no-record"),
])
def test_a_recorder_fault_it_cannot_apply_is_one_line_and_exit_2(argv, says, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert says in err and err.count("\n") == 1, err
    assert main(["run", "--fault", "kill:recorder:3", "--check"]) == 0


def test_the_sweep_figure_plots_bills_and_penalties_against_the_setting_with_its_unit_intervals_apart():
    """A numeric setting swept over seeds: the bill and the penalty each in a row of panels, the setting and its unit
    on the x-axis, and each agent's interval at an x of its own, so that no two agents' intervals overlap."""
    import pandas as pd  # noqa: PLC0415

    from dmosim.results.sweeps import sweep_figure  # noqa: PLC0415

    rows = []
    for penalty in (50, 150, 300):
        for seed in (1, 2, 3):
            settled = {agent: {"total": 1000.0 + seed, "deviation_penalty": penalty + 10.0 * seed}
                       for agent in ("mg1", "mg2", "mg3")}
            rows += sweep_rows({"market.penalty": penalty, "seed": seed}, f"{penalty}-{seed}", "r", 1.0,
                               typed({"settlement": settled, "verdict": verdict([])}))
    figure = sweep_figure(pd.DataFrame(rows), ["market.penalty", "seed"])
    top, bottom = figure.axes[:2]
    assert bottom.get_xlabel() == "market.penalty ($/MWh)" and "$" in top.get_ylabel() and "$" in bottom.get_ylabel()
    assert "penalty" in bottom.get_ylabel() and "bill" in top.get_ylabel()
    penalties = [line for line in bottom.get_lines() if line.get_marker() == "o"]
    assert [list(line.get_ydata()) for line in penalties] == [[70.0, 170.0, 320.0]] * 3  # the penalty, not the bill
    for ax in (top, bottom):
        xs = sorted(x for line in ax.get_lines() if line.get_marker() == "o" for x in line.get_xdata())
        assert len(xs) == len(set(xs)) == 9  # 3 agents at 3 settings, none at another's x
